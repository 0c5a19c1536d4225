#include "server/net/dicomweb/http.h"

#include <curl/curl.h>

#include <fstream>
#include <mutex>
#include <sstream>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "server/node/peer.h"

namespace interslice::server::dicomweb {
namespace {

void GlobalInitOnce() {
  static std::once_flag once;
  std::call_once(once, [] { curl_global_init(CURL_GLOBAL_DEFAULT); });
}

// The file's text without surrounding white space (a token or a password;
// a trailing newline is the usual way such files end).
absl::StatusOr<std::string> ReadSecret(const node::DicomPeer& peer,
                                       const char* key,
                                       const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  std::stringstream text;
  if (in.is_open()) text << in.rdbuf();
  std::string secret(absl::StripAsciiWhitespace(text.str()));
  if (!in.is_open() || secret.empty()) {
    return absl::FailedPreconditionError(
        absl::StrCat(node::PeerLabel(peer), ": ", key, " '", path,
                     "' cannot be read or is empty"));
  }
  return secret;
}

}  // namespace

struct HttpRequest::Impl {
  CURL* curl = nullptr;
  curl_slist* headers = nullptr;
  std::string label;
  char error[CURL_ERROR_SIZE] = {};
  BodySource source;
  BodySink sink;
  absl::Status abort_status;
  std::string content_type;
  // Kept alive for curl (it does not copy every option).
  std::string url, secret_header, user, password;

  static size_t Read(char* buffer, size_t size, size_t n, void* self) {
    Impl* impl = static_cast<Impl*>(self);
    const int64_t got = impl->source(buffer, size * n);
    if (got < 0) return CURL_READFUNC_ABORT;
    return static_cast<size_t>(got);
  }
  static size_t Write(char* data, size_t size, size_t n, void* self) {
    Impl* impl = static_cast<Impl*>(self);
    if (!impl->sink) return size * n;  // discarded
    // Returning less than given makes curl abort with CURLE_WRITE_ERROR.
    return impl->sink(data, size * n) ? size * n : 0;
  }
  static size_t Header(char* data, size_t size, size_t n, void* self) {
    Impl* impl = static_cast<Impl*>(self);
    absl::string_view line(data, size * n);
    if (absl::StartsWithIgnoreCase(line, "content-type:")) {
      impl->content_type =
          std::string(absl::StripAsciiWhitespace(line.substr(13)));
    }
    return size * n;
  }
};

HttpRequest::HttpRequest() : impl_(std::make_unique<Impl>()) {}

HttpRequest::~HttpRequest() {
  if (impl_->headers != nullptr) curl_slist_free_all(impl_->headers);
  if (impl_->curl != nullptr) curl_easy_cleanup(impl_->curl);
}

absl::StatusOr<std::unique_ptr<HttpRequest>> HttpRequest::Make(
    const node::DicomPeer& peer, const std::string& url, int timeout_seconds) {
  GlobalInitOnce();
  std::unique_ptr<HttpRequest> request(new HttpRequest());
  Impl& impl = *request->impl_;
  impl.label = node::PeerLabel(peer);
  impl.curl = curl_easy_init();
  if (impl.curl == nullptr) {
    return absl::InternalError("cannot make an HTTP request (curl_easy_init)");
  }
  CURL* curl = impl.curl;
  const node::DicomWebEndpoint& web = peer.web;
  impl.url = url;
  curl_easy_setopt(curl, CURLOPT_URL, impl.url.c_str());
  curl_easy_setopt(curl, CURLOPT_ERRORBUFFER, impl.error);
  curl_easy_setopt(curl, CURLOPT_NOSIGNAL, 1L);  // threads; no SIGALRM
  curl_easy_setopt(curl, CURLOPT_PROTOCOLS_STR, "http,https");
  curl_easy_setopt(curl, CURLOPT_FOLLOWLOCATION, 0L);  // credentials stay put
  curl_easy_setopt(curl, CURLOPT_CONNECTTIMEOUT,
                   static_cast<long>(timeout_seconds));
  // Less than 1 byte/s for timeout_seconds: stalled.
  curl_easy_setopt(curl, CURLOPT_LOW_SPEED_LIMIT, 1L);
  curl_easy_setopt(curl, CURLOPT_LOW_SPEED_TIME,
                   static_cast<long>(timeout_seconds));
  curl_easy_setopt(curl, CURLOPT_TCP_NODELAY, 1L);
  curl_easy_setopt(curl, CURLOPT_WRITEFUNCTION, &Impl::Write);
  curl_easy_setopt(curl, CURLOPT_WRITEDATA, &impl);
  curl_easy_setopt(curl, CURLOPT_HEADERFUNCTION, &Impl::Header);
  curl_easy_setopt(curl, CURLOPT_HEADERDATA, &impl);
  if (!web.bearer_token_file.empty()) {
    absl::StatusOr<std::string> token =
        ReadSecret(peer, "bearer_token_file", web.bearer_token_file);
    if (!token.ok()) return token.status();
    impl.secret_header = absl::StrCat("Authorization: Bearer ", *token);
    impl.headers = curl_slist_append(impl.headers, impl.secret_header.c_str());
  }
  if (!web.basic_user.empty()) {
    absl::StatusOr<std::string> password =
        ReadSecret(peer, "basic_password_file", web.basic_password_file);
    if (!password.ok()) return password.status();
    impl.user = web.basic_user;
    impl.password = *password;
    curl_easy_setopt(curl, CURLOPT_HTTPAUTH, CURLAUTH_BASIC);
    curl_easy_setopt(curl, CURLOPT_USERNAME, impl.user.c_str());
    curl_easy_setopt(curl, CURLOPT_PASSWORD, impl.password.c_str());
  }
  if (!web.client_certificate.empty()) {
    curl_easy_setopt(curl, CURLOPT_SSLCERT, web.client_certificate.c_str());
    curl_easy_setopt(curl, CURLOPT_SSLCERTTYPE, "PEM");
    curl_easy_setopt(curl, CURLOPT_SSLKEY, web.client_key.c_str());
    curl_easy_setopt(curl, CURLOPT_SSLKEYTYPE, "PEM");
  }
  if (!web.ca_certificates.empty()) {
    curl_easy_setopt(curl, CURLOPT_CAINFO, web.ca_certificates.c_str());
  }
  // Verification stays on (curl's default): a DICOMweb peer over https is
  // authenticated by its certificate.
  return request;
}

void HttpRequest::AddHeader(const std::string& line) {
  impl_->headers = curl_slist_append(impl_->headers, line.c_str());
}

void HttpRequest::SetPostBody(BodySource source, int64_t size) {
  impl_->source = std::move(source);
  curl_easy_setopt(impl_->curl, CURLOPT_POST, 1L);
  curl_easy_setopt(impl_->curl, CURLOPT_READFUNCTION, &Impl::Read);
  curl_easy_setopt(impl_->curl, CURLOPT_READDATA, impl_.get());
  curl_easy_setopt(impl_->curl, CURLOPT_POSTFIELDSIZE_LARGE,
                   static_cast<curl_off_t>(size));
  // No "Expect: 100-continue" round trip before each request body.
  AddHeader("Expect:");
}

void HttpRequest::SetSink(BodySink sink) { impl_->sink = std::move(sink); }

void HttpRequest::SetAbortStatus(absl::Status status) {
  if (impl_->abort_status.ok()) impl_->abort_status = std::move(status);
}

std::string HttpRequest::content_type() const { return impl_->content_type; }

absl::StatusOr<long> HttpRequest::Perform() {
  curl_easy_setopt(impl_->curl, CURLOPT_HTTPHEADER, impl_->headers);
  const CURLcode code = curl_easy_perform(impl_->curl);
  if (!impl_->abort_status.ok()) return impl_->abort_status;
  if (code != CURLE_OK) {
    const std::string reason =
        impl_->error[0] != '\0' ? impl_->error : curl_easy_strerror(code);
    return absl::UnavailableError(
        absl::StrCat("cannot reach ", impl_->label, ": ", reason));
  }
  long http = 0;
  curl_easy_getinfo(impl_->curl, CURLINFO_RESPONSE_CODE, &http);
  return http;
}

absl::Status HttpStatusError(const node::DicomPeer& peer,
                             const std::string& what, long http_status) {
  const std::string head =
      absl::StrCat(what, " to ", node::PeerLabel(peer), ": HTTP ", http_status);
  if (http_status == 401 || http_status == 403) {
    return absl::PermissionDeniedError(absl::StrCat(
        head, http_status == 401
                  ? ": the peer did not accept our credentials (check "
                    "bearer_token_file or basic_user/basic_password_file, or "
                    "client_certificate)"
                  : ": the peer refuses this user access (authorization)"));
  }
  if (http_status >= 500 || http_status == 429 || http_status == 408) {
    return absl::UnavailableError(
        absl::StrCat(head, ": the peer is failing or busy"));
  }
  return absl::FailedPreconditionError(absl::StrCat(
      head, http_status == 404 ? ": not found (is url the DICOMweb base URL?)"
                               : ": unexpected answer"));
}

BoundedBody::BoundedBody(HttpRequest& request, size_t limit, std::string what)
    : request_(request), limit_(limit), what_(std::move(what)) {
  request_.SetSink([this](const char* data, size_t n) {
    if (text_.size() + n > limit_) {
      request_.SetAbortStatus(absl::FailedPreconditionError(absl::StrCat(
          what_, ": the answer is larger than ", limit_, " bytes; not read")));
      return false;
    }
    text_.append(data, n);
    return true;
  });
}

bool IsDicomJson(const std::string& content_type) {
  const std::string lower = absl::AsciiStrToLower(content_type);
  return absl::StartsWith(lower, "application/dicom+json") ||
         absl::StartsWith(lower, "application/json");
}

const nlohmann::json* DicomJsonValue(const nlohmann::json& dataset,
                                     const char* tag) {
  if (!dataset.is_object()) return nullptr;
  const auto it = dataset.find(tag);
  if (it == dataset.end() || !it->is_object()) return nullptr;
  const auto value = it->find("Value");
  if (value == it->end() || !value->is_array()) return nullptr;
  return &*value;
}

std::string DicomJsonText(const nlohmann::json& dataset, const char* tag) {
  const nlohmann::json* values = DicomJsonValue(dataset, tag);
  if (values == nullptr) return "";
  std::string out;
  for (size_t i = 0; i < values->size(); ++i) {
    const nlohmann::json& v = (*values)[i];
    if (i > 0) out.push_back('\\');
    if (v.is_string()) {
      out += v.get<std::string>();
    } else if (v.is_number_integer()) {
      absl::StrAppend(&out, v.get<int64_t>());
    } else if (v.is_number()) {
      absl::StrAppend(&out, v.get<double>());
    } else if (v.is_object() && v.contains("Alphabetic") &&
               v["Alphabetic"].is_string()) {
      out += v["Alphabetic"].get<std::string>();
    }
  }
  return out;
}

std::string EscapePathSegment(const std::string& text) {
  std::string out;
  for (unsigned char c : text) {
    if (absl::ascii_isalnum(c) || c == '.' || c == '-' || c == '_' ||
        c == '~') {
      out.push_back(static_cast<char>(c));
    } else {
      absl::StrAppendFormat(&out, "%%%02X", c);
    }
  }
  return out;
}

}  // namespace interslice::server::dicomweb
