#include "tests/testing/orthanc.h"

#include <curl/curl.h>
#include <sys/wait.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "tests/testing/process.h"
#include "tests/testing/tools.h"
#include "tests/testing/wait_for.h"

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

absl::StatusOr<std::unique_ptr<Orthanc>> Orthanc::Start(
    const std::string& dir, std::vector<OrthancModality> modalities,
    const std::string& ae_title, OrthancExtras extras) {
  static std::once_flag curl_once;
  std::call_once(curl_once, [] { curl_global_init(CURL_GLOBAL_DEFAULT); });
  const std::string binary = FindTool("Orthanc", {"/usr/sbin"});
  if (binary.empty()) {
    return absl::FailedPreconditionError(
        "Orthanc is not installed (not on PATH nor in /usr/sbin; "
        "scripts/install-deps.sh installs Debian's orthanc)");
  }
  std::unique_ptr<Orthanc> o(new Orthanc());
  o->binary_ = binary;
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
  if (extras.dicomweb) {
    const char* plugin = "/usr/share/orthanc/plugins/libOrthancDicomWeb.so";
    if (!fs::exists(plugin)) {
      return absl::FailedPreconditionError(
          absl::StrCat("Orthanc's DICOMweb plugin is not installed (", plugin,
                       "; scripts/install-deps.sh installs orthanc-dicomweb)"));
    }
    config["Plugins"] = nlohmann::json::array({plugin});
    config["DicomWeb"] = {{"Enable", true}, {"Root", "/dicom-web/"}};
    nlohmann::json servers = nlohmann::json::object();
    for (const OrthancExtras::DicomWebServer& server :
         extras.dicomweb_servers) {
      servers[server.name] =
          server.user.empty() ? nlohmann::json::array({server.url})
                              : nlohmann::json::array(
                                    {server.url, server.user, server.password});
    }
    if (!servers.empty()) config["DicomWeb"]["Servers"] = servers;
  }
  if (!extras.users.empty()) {
    config["AuthenticationEnabled"] = true;
    nlohmann::json users = nlohmann::json::object();
    for (const auto& [name, password] : extras.users) users[name] = password;
    config["RegisteredUsers"] = users;
    o->user_ = extras.users.front().first;
    o->password_ = extras.users.front().second;
  }
  if (!extras.lua_script.empty()) {
    const std::string lua = (fs::path(dir) / "script.lua").string();
    std::ofstream(lua) << extras.lua_script;
    config["LuaScripts"] = nlohmann::json::array({lua});
  }
  o->config_path_ = (fs::path(dir) / "orthanc.json").string();
  // A port found free may be taken by another process (ctest runs two tests
  // at once) before Orthanc binds it; then Orthanc exits at start-up saying
  // so, and it gets two other ports. Any other start-up failure is returned.
  absl::Status launched;
  for (int attempt = 0; attempt < 3; ++attempt) {
    if (attempt > 0) {
      o->http_port_ = FreeTcpPort();
      o->dicom_port_ = FreeTcpPort();
      config["HttpPort"] = o->http_port_;
      config["DicomPort"] = o->dicom_port_;
    }
    std::ofstream(o->config_path_, std::ios::trunc) << config.dump(2);
    launched = o->Launch();
    if (launched.ok() ||
        !absl::StrContains(launched.message(), "already in use")) {
      break;
    }
  }
  if (!launched.ok()) return launched;
  return o;
}

absl::Status Orthanc::Launch() {
  pid_ = StartProcess({binary_, config_path_},
                      (fs::path(dir_) / "orthanc.log").string());
  bool ended = false;
  const bool up = WaitFor(
      [&] {
        if (WaitProcess(pid_, 0) != -1 ||
            ::waitpid(pid_, nullptr, WNOHANG) < 0) {
          ended = true;
          return true;
        }
        return Get("/system").ok();
      },
      std::chrono::seconds(60), std::chrono::milliseconds(50));
  if (ended) {
    pid_ = -1;
    return absl::FailedPreconditionError(
        absl::StrCat("Orthanc exited at start-up; its log:\n", log()));
  }
  if (!up) {
    Stop();
    return absl::DeadlineExceededError(absl::StrCat(
        "Orthanc's REST API did not answer in 60 s; its log:\n", log()));
  }
  return absl::OkStatus();
}

Orthanc::~Orthanc() { Stop(); }

std::string Orthanc::dicomweb_url() const {
  return absl::StrCat("http://127.0.0.1:", http_port_, "/dicom-web");
}

void Orthanc::Stop() {
  if (pid_ <= 0) return;
  StopProcess(pid_, 30);
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
  if (!user_.empty()) {
    curl_easy_setopt(curl, CURLOPT_HTTPAUTH, CURLAUTH_BASIC);
    curl_easy_setopt(curl, CURLOPT_USERNAME, user_.c_str());
    curl_easy_setopt(curl, CURLOPT_PASSWORD, password_.c_str());
  }
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
