// A loopback HTTP/1.1 endpoint that answers each request with bytes the
// test chooses, for the answers a real DICOMweb server does not give: an
// HTML page where DICOM JSON belongs, a multipart part cut short or longer
// than announced, a QIDO answer that lies about sizes. One connection per
// request (it answers "Connection: close" semantics by closing); a thread
// of its own; stops in its destructor. Real servers (Orthanc with its
// DICOMweb plugin) are used for everything they can show.
#ifndef INTERSLICE_TESTS_TESTING_CANNED_HTTP_H_
#define INTERSLICE_TESTS_TESTING_CANNED_HTTP_H_

#include <atomic>
#include <functional>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

namespace interslice::testing {

struct CannedRequest {
  std::string method, target;  // "POST", "/dicom-web/studies"
  std::string head;            // the request line and headers as sent
  size_t body_bytes = 0;       // read and discarded
};

class CannedHttp {
 public:
  // `answer` returns the whole raw response (status line, headers, body)
  // for a request; the connection is closed after it is written.
  using Answer = std::function<std::string(const CannedRequest&)>;
  explicit CannedHttp(Answer answer);
  ~CannedHttp();
  int port() const { return port_; }
  std::string url(const std::string& path = "") const;
  std::vector<CannedRequest> requests();

  // "HTTP/1.1 <status>\r\nContent-Type: <type>\r\nContent-Length: N\r\n
  // Connection: close\r\n\r\n<body>".
  static std::string Response(int status, const std::string& content_type,
                              const std::string& body);

 private:
  void Serve();
  Answer answer_;
  int listener_ = -1;
  int port_ = 0;
  std::atomic<bool> stop_{false};
  std::mutex mu_;
  std::vector<CannedRequest> requests_;
  std::thread thread_;
};

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_CANNED_HTTP_H_
