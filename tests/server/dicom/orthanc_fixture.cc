#include "tests/server/dicom/orthanc_fixture.h"

#include <arpa/inet.h>
#include <curl/curl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "tests/server/process.h"

namespace interslice::testing {
namespace fs = std::filesystem;
namespace {

size_t Append(char* data, size_t size, size_t n, void* out) {
  static_cast<std::string*>(out)->append(data, size * n);
  return size * n;
}

bool IsPart10(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  char magic[132] = {};
  return in.read(magic, sizeof(magic)) && std::string(magic + 128, 4) == "DICM";
}

}  // namespace

int FreeTcpPort() {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  addr.sin_port = 0;
  socklen_t len = sizeof(addr);
  int port = 0;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof(addr)) == 0 &&
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&addr), &len) == 0) {
    port = ntohs(addr.sin_port);
  }
  ::close(fd);
  return port;
}

absl::StatusOr<std::unique_ptr<Orthanc>> Orthanc::Start(
    const std::string& dir, std::vector<OrthancModality> modalities,
    const std::string& ae_title) {
  static std::once_flag curl_once;
  std::call_once(curl_once, [] { curl_global_init(CURL_GLOBAL_DEFAULT); });
  if (!fs::exists(kOrthancBinary)) {
    return absl::FailedPreconditionError(
        "Orthanc is not installed (scripts/install-deps.sh installs it)");
  }
  std::unique_ptr<Orthanc> o(new Orthanc());
  o->dir_ = dir;
  o->ae_title_ = ae_title;
  o->http_port_ = FreeTcpPort();
  o->dicom_port_ = FreeTcpPort();
  fs::create_directories(fs::path(dir) / "storage");
  nlohmann::json config = {
      {"Name", "interslice-test"},
      {"StorageDirectory", (fs::path(dir) / "storage").string()},
      {"IndexDirectory", (fs::path(dir) / "storage").string()},
      {"HttpPort", o->http_port_},
      {"DicomPort", o->dicom_port_},
      {"DicomAet", ae_title},
      {"RemoteAccessAllowed", false},
      {"AuthenticationEnabled", false},
      {"HttpServerEnabled", true},
      {"DicomServerEnabled", true},
      {"DicomCheckCalledAet", false},
      {"DicomAlwaysAllowEcho", true},
      {"DicomAlwaysAllowStore", true},
      {"DicomAlwaysAllowFind", true},
      {"DicomAlwaysAllowGet", true},
      {"DicomAlwaysAllowMove", true},
      {"DicomScuTimeout", 10},
      {"StableAge", 2},
      {"SaveJobs", false},
      {"Plugins", nlohmann::json::array()},
      {"ConcurrentJobs", 1},
      {"HttpThreadsCount", 10},
  };
  nlohmann::json m = nlohmann::json::object();
  for (const OrthancModality& modality : modalities) {
    m[modality.name] = {{"AET", modality.ae_title}, {"Host", modality.host},
                        {"Port", modality.port},    {"AllowEcho", true},
                        {"AllowStore", true},       {"AllowFind", true},
                        {"AllowGet", true},         {"AllowMove", true}};
  }
  config["DicomModalities"] = m;
  o->config_path_ = (fs::path(dir) / "orthanc.json").string();
  std::ofstream(o->config_path_) << config.dump(2);
  if (absl::Status s = o->Launch(); !s.ok()) return s;
  return o;
}

absl::Status Orthanc::Launch() {
  pid_ = StartProcess({kOrthancBinary, config_path_},
                      (fs::path(dir_) / "orthanc.log").string());
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (std::chrono::steady_clock::now() < end) {
    if (Get("/system").ok()) return absl::OkStatus();
    if (WaitProcess(pid_, 0) != -1) {
      pid_ = -1;
      return absl::InternalError(
          absl::StrCat("Orthanc exited at start-up; its log:\n", log()));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  Stop();
  return absl::DeadlineExceededError(absl::StrCat(
      "Orthanc's REST API did not answer in 30 s; its log:\n", log()));
}

Orthanc::~Orthanc() { Stop(); }

void Orthanc::Stop() {
  if (pid_ <= 0) return;
  ::kill(pid_, SIGTERM);
  if (WaitProcess(pid_, 10) == -1) {
    ::kill(pid_, SIGKILL);
    WaitProcess(pid_, 10);
  }
  pid_ = -1;
}

absl::Status Orthanc::Restart() {
  Stop();
  return Launch();
}

std::string Orthanc::log() const {
  return ReadFileOrEmpty((fs::path(dir_) / "orthanc.log").string());
}

absl::StatusOr<std::string> Orthanc::Request(const std::string& method,
                                             const std::string& path,
                                             const std::string& body) const {
  CURL* curl = curl_easy_init();
  if (curl == nullptr) return absl::InternalError("curl_easy_init failed");
  const std::string url = absl::StrCat("http://127.0.0.1:", http_port_, path);
  std::string response;
  curl_easy_setopt(curl, CURLOPT_URL, url.c_str());
  curl_easy_setopt(curl, CURLOPT_WRITEFUNCTION, &Append);
  curl_easy_setopt(curl, CURLOPT_WRITEDATA, &response);
  curl_easy_setopt(curl, CURLOPT_TIMEOUT, 60L);
  curl_easy_setopt(curl, CURLOPT_NOSIGNAL, 1L);
  curl_easy_setopt(curl, CURLOPT_NOPROXY, "*");
  if (method == "POST") {
    curl_easy_setopt(curl, CURLOPT_POST, 1L);
    curl_easy_setopt(curl, CURLOPT_POSTFIELDS, body.data());
    curl_easy_setopt(curl, CURLOPT_POSTFIELDSIZE_LARGE,
                     static_cast<curl_off_t>(body.size()));
  } else if (method != "GET") {
    curl_easy_setopt(curl, CURLOPT_CUSTOMREQUEST, method.c_str());
  }
  const CURLcode code = curl_easy_perform(curl);
  long http = 0;
  curl_easy_getinfo(curl, CURLINFO_RESPONSE_CODE, &http);
  curl_easy_cleanup(curl);
  if (code != CURLE_OK) {
    return absl::UnavailableError(
        absl::StrCat(method, " ", path, ": ", curl_easy_strerror(code)));
  }
  if (http >= 400) {
    return absl::FailedPreconditionError(
        absl::StrCat(method, " ", path, ": HTTP ", http, ": ", response));
  }
  return response;
}

absl::StatusOr<std::string> Orthanc::Get(const std::string& path) const {
  return Request("GET", path, "");
}

absl::StatusOr<nlohmann::json> Orthanc::GetJson(const std::string& path) const {
  absl::StatusOr<std::string> body = Get(path);
  if (!body.ok()) return body.status();
  nlohmann::json j = nlohmann::json::parse(*body, nullptr, false);
  if (j.is_discarded()) {
    return absl::InternalError(absl::StrCat("GET ", path, ": not JSON"));
  }
  return j;
}

absl::StatusOr<nlohmann::json> Orthanc::PostJson(
    const std::string& path, const std::string& body) const {
  absl::StatusOr<std::string> response = Request("POST", path, body);
  if (!response.ok()) return response.status();
  nlohmann::json j = nlohmann::json::parse(*response, nullptr, false);
  if (j.is_discarded()) {
    return absl::InternalError(absl::StrCat("POST ", path, ": not JSON"));
  }
  return j;
}

absl::StatusOr<std::string> Orthanc::Upload(const std::string& file) const {
  absl::StatusOr<nlohmann::json> j =
      PostJson("/instances", ReadFileOrEmpty(file));
  if (!j.ok()) return j.status();
  if (!j->contains("ID")) {
    return absl::InternalError(absl::StrCat("upload answered ", j->dump()));
  }
  return (*j)["ID"].get<std::string>();
}

absl::StatusOr<int> Orthanc::UploadFolder(const std::string& dir) const {
  int n = 0;
  for (const auto& entry : fs::recursive_directory_iterator(dir)) {
    if (!entry.is_regular_file() || !IsPart10(entry.path())) continue;
    absl::StatusOr<std::string> id = Upload(entry.path().string());
    if (!id.ok()) return id.status();
    ++n;
  }
  return n;
}

absl::StatusOr<std::string> Orthanc::InstanceFile(const std::string& id) const {
  return Get(absl::StrCat("/instances/", id, "/file"));
}

}  // namespace interslice::testing
