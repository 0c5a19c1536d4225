// Time as the server's parts read it: the real clocks, or a test's
// (tests/testing/fake_clock.h), passed in like every other dependency so
// that waits (a series' stable wait, a retention) can be tested without
// sleeping.
#ifndef INTERSLICE_SERVER_BASE_CLOCK_H_
#define INTERSLICE_SERVER_BASE_CLOCK_H_

#include <chrono>
#include <cstdint>

namespace interslice::server {

class Clock {
 public:
  virtual ~Clock() = default;
  // Monotonic time, for waits and durations.
  virtual std::chrono::steady_clock::time_point Now() const = 0;
  // Wall-clock time in milliseconds since the Unix epoch, for records.
  virtual int64_t UnixMillis() const = 0;

  // std::chrono's steady and system clocks; lives for the whole process.
  static const Clock* Real();
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_BASE_CLOCK_H_
