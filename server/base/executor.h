// A small fixed pool of threads running posted tasks in FIFO order. gRPC
// reactors hand every blocking step (file writes and reads, fsync, directory
// creation and removal) to it, so that no reactor callback ever blocks.
#ifndef INTERSLICE_SERVER_BASE_EXECUTOR_H_
#define INTERSLICE_SERVER_BASE_EXECUTOR_H_

#include <condition_variable>
#include <deque>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace interslice::server {

class Executor {
 public:
  explicit Executor(int threads);
  // Runs the tasks already posted, then joins the threads.
  ~Executor();
  Executor(const Executor&) = delete;
  Executor& operator=(const Executor&) = delete;

  void Post(std::function<void()> task);

 private:
  void Loop();

  std::mutex mu_;
  std::condition_variable cv_;
  std::deque<std::function<void()>> tasks_;
  bool stopping_ = false;
  std::vector<std::thread> threads_;
};

}  // namespace interslice::server

#endif  // INTERSLICE_SERVER_BASE_EXECUTOR_H_
