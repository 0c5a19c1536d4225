#include "client/progress_display.h"

#include <unistd.h>

#include "absl/strings/str_format.h"

namespace interslice::client {

ProgressDisplay::ProgressDisplay(std::FILE* stream, bool enabled)
    : stream_(stream),
      active_(enabled && isatty(fileno(stream)) != 0),
      start_(std::chrono::steady_clock::now()) {}

void ProgressDisplay::Update(const ProgressEvent& event) {
  if (!active_) return;
  std::lock_guard<std::mutex> lock(mutex_);
  const auto now = std::chrono::steady_clock::now();
  // Redraw at most 10 times a second, but always on a stage change.
  if (event.stage == last_stage_ &&
      now - last_draw_ < std::chrono::milliseconds(100)) {
    return;
  }
  last_draw_ = now;
  last_stage_ = event.stage;
  const double elapsed = std::chrono::duration<double>(now - start_).count();
  std::string line = absl::StrFormat("[%6.1fs] %-8s %3.0f%%", elapsed,
                                     event.stage, 100 * event.fraction);
  if (event.iteration >= 0) {
    absl::StrAppendFormat(&line, "  iteration %d  residual %.3g  energy %.6g",
                          event.iteration, event.relative_residual,
                          event.energy);
  }
  const size_t width = line.size();
  if (width < last_width_) line.append(last_width_ - width, ' ');
  last_width_ = width;
  std::fprintf(stream_, "\r%s", line.c_str());
  std::fflush(stream_);
}

void ProgressDisplay::Finish() {
  if (!active_) return;
  std::lock_guard<std::mutex> lock(mutex_);
  std::fprintf(stream_, "\r%s\r", std::string(last_width_, ' ').c_str());
  std::fflush(stream_);
}

}  // namespace interslice::client
