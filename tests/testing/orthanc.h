// A real Orthanc PACS for the DICOM network tests: Debian's `Orthanc`
// binary started as a child process on loopback with a configuration the
// test writes (free HTTP and DICOM ports, its own storage folder, the
// interslice server as a known modality), and a small REST client over
// libcurl.
//
//   auto orthanc = Orthanc::Start(dir / "orthanc",
//                                 {{"interslice", "INTERSLICE", "127.0.0.1",
//                                   server.dicom_port()}});
//   ASSERT_TRUE(orthanc.ok()) << orthanc.status();
//   (*orthanc)->UploadFolder(series);  (*orthanc)->GetJson("/studies");
//
// Orthanc missing (not on PATH nor in /usr/sbin) is an error naming it, so
// a test that needs the PACS fails instead of passing without one.
#ifndef INTERSLICE_TESTS_TESTING_ORTHANC_H_
#define INTERSLICE_TESTS_TESTING_ORTHANC_H_

#include <sys/types.h>

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "nlohmann/json.hpp"

namespace interslice::testing {

struct OrthancModality {
  std::string name;  // Orthanc's name for it (REST /modalities/{name})
  std::string ae_title;
  std::string host = "127.0.0.1";
  int port = 0;
};

// What a test may add to the PACS.
struct OrthancExtras {
  // Loads Debian's DICOMweb plugin (orthanc-dicomweb), served at
  // dicomweb_url() (http://127.0.0.1:PORT/dicom-web).
  bool dicomweb = false;
  // HTTP basic users (name, password): with any, authentication is on for
  // the REST API and DICOMweb alike (the fixture's own REST calls use the
  // first user).
  std::vector<std::pair<std::string, std::string>> users;
  // A Lua script (text) Orthanc runs, e.g. a ReceivedInstanceFilter.
  std::string lua_script;
  // DICOMweb servers Orthanc's plugin may send to (with `dicomweb`):
  // POST /dicom-web/servers/{name}/stow {"Resources": [...]} makes Orthanc
  // a STOW-RS client of `url` (HTTP basic with user and password when
  // given).
  struct DicomWebServer {
    std::string name, url, user, password;
  };
  std::vector<DicomWebServer> dicomweb_servers;
};

class Orthanc {
 public:
  // Writes <dir>/orthanc.json and starts Orthanc with storage in
  // <dir>/storage on two free ports; waits (polling, up to 60 s) until its
  // REST API answers. Errors: FailedPrecondition when Orthanc is not
  // installed or ends at start-up, DeadlineExceeded (with its log).
  // Modalities may C-STORE, C-GET, C-FIND and C-MOVE with it.
  static absl::StatusOr<std::unique_ptr<Orthanc>> Start(
      const std::string& dir, std::vector<OrthancModality> modalities,
      const std::string& ae_title = "ORTHANC", OrthancExtras extras = {});
  ~Orthanc();  // Stop()

  // SIGTERM, wait (SIGKILL after 30 s). Storage stays: Restart() brings the
  // same PACS back on the same ports.
  void Stop();
  absl::Status Restart();
  bool running() const { return pid_ > 0; }
  // The Orthanc process (a child of the test), e.g. to kill it mid-send.
  pid_t pid() const { return pid_; }

  const std::string& ae_title() const { return ae_title_; }
  int dicom_port() const { return dicom_port_; }
  int http_port() const { return http_port_; }
  // The DICOMweb base URL (with OrthancExtras::dicomweb).
  std::string dicomweb_url() const;
  std::string log() const;

  // REST. Errors for transport failures and HTTP status >= 400.
  absl::StatusOr<std::string> Get(const std::string& path) const;
  absl::StatusOr<nlohmann::json> GetJson(const std::string& path) const;
  absl::StatusOr<nlohmann::json> PostJson(const std::string& path,
                                          const std::string& body) const;
  // POST /instances with the file's bytes: Orthanc's instance id.
  absl::StatusOr<std::string> Upload(const std::string& file) const;
  // Every Part 10 file under `dir` uploaded; how many.
  absl::StatusOr<int> UploadFolder(const std::string& dir) const;

  // The DICOM file of an Orthanc instance id.
  absl::StatusOr<std::string> InstanceFile(const std::string& id) const;

 private:
  Orthanc() = default;
  absl::Status Launch();
  absl::StatusOr<std::string> Request(const std::string& method,
                                      const std::string& path,
                                      const std::string& body) const;

  std::string binary_;
  std::string dir_;
  std::string config_path_;
  std::string ae_title_;
  std::string user_, password_;  // REST credentials (none: empty)
  int http_port_ = 0;
  int dicom_port_ = 0;
  pid_t pid_ = -1;
};

}  // namespace interslice::testing

#endif  // INTERSLICE_TESTS_TESTING_ORTHANC_H_
