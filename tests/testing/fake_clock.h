// A clock a test moves by hand (server/base/clock.h), so that waits are
// tested without sleeping. Thread-safe.
#ifndef INTERSLICE_TESTS_TESTING_FAKE_CLOCK_H_
#define INTERSLICE_TESTS_TESTING_FAKE_CLOCK_H_

#include <atomic>
#include <chrono>
#include <cstdint>

#include "server/base/clock.h"

namespace interslice::testing {

class FakeClock : public server::Clock {
 public:
  // Starts at the real clocks' present, then moves only by Advance.
  FakeClock()
      : steady_(std::chrono::steady_clock::now().time_since_epoch().count()),
        unix_ms_(server::Clock::Real()->UnixMillis()) {}

  std::chrono::steady_clock::time_point Now() const override {
    return std::chrono::steady_clock::time_point(
        std::chrono::steady_clock::duration(steady_.load()));
  }
  int64_t UnixMillis() const override { return unix_ms_.load(); }

  void Advance(std::chrono::steady_clock::duration by) {
    steady_ += by.count();
    unix_ms_ +=
        std::chrono::duration_cast<std::chrono::milliseconds>(by).count();
  }

 private:
  std::atomic<std::chrono::steady_clock::rep> steady_;
  std::atomic<int64_t> unix_ms_;
};

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_FAKE_CLOCK_H_
