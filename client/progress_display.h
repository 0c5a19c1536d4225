// A one-line progress display for a terminal (rewritten in place with \r).
#ifndef INTERSLICE_CLIENT_PROGRESS_DISPLAY_H_
#define INTERSLICE_CLIENT_PROGRESS_DISPLAY_H_

#include <chrono>
#include <cstdio>
#include <mutex>
#include <string>

#include "core/common/compute.h"

namespace interslice::client {

class ProgressDisplay {
 public:
  // Draws only when `stream` is a terminal and `enabled`.
  ProgressDisplay(std::FILE* stream, bool enabled);
  void Update(const ProgressEvent& event);
  // Clears the line (call before printing anything else).
  void Finish();

 private:
  std::FILE* stream_;
  bool active_;
  std::mutex mutex_;
  std::chrono::steady_clock::time_point start_;
  std::chrono::steady_clock::time_point last_draw_{};
  std::string last_stage_;
  size_t last_width_ = 0;
};

}  // namespace interslice::client

#endif  // INTERSLICE_CLIENT_PROGRESS_DISPLAY_H_
