// Polling with a deadline, in place of sleeps used as synchronisation: a
// test waits exactly as long as the condition takes (fast on an idle
// machine), and a deadline far above the expected time (seconds to minutes,
// not milliseconds) bounds a failure, so the test neither flakes on a loaded
// machine nor hangs. A sleep stays legitimate only where a test checks that
// something does NOT happen within a time; say so next to it.
#ifndef INTERSLICE_TESTS_TESTING_WAIT_FOR_H_
#define INTERSLICE_TESTS_TESTING_WAIT_FOR_H_

#include <chrono>
#include <thread>

namespace interslice::testing {

// Calls `done` until it returns true or `timeout` has passed, pausing
// `interval` between calls; whether it returned true. It is called at least
// once, and once more at the deadline.
template <typename Predicate, typename Rep, typename Period>
bool WaitFor(
    Predicate&& done, std::chrono::duration<Rep, Period> timeout,
    std::chrono::milliseconds interval = std::chrono::milliseconds(20)) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < deadline) {
    if (done()) return true;
    std::this_thread::sleep_for(interval);
  }
  return done();
}

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_WAIT_FOR_H_
