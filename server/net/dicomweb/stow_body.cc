#include "server/net/dicomweb/stow_body.h"

#include <algorithm>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"

namespace interslice::server::dicomweb {
namespace {

// Debian's abseil has its own string_view type.
absl::string_view A(std::string_view v) { return {v.data(), v.size()}; }
std::string_view Strip(std::string_view v) {
  const absl::string_view s = absl::StripAsciiWhitespace(A(v));
  return {s.data(), s.size()};
}

constexpr int kMaxHeaderLines = 64;
// Transport padding after a boundary (RFC 2046 5.1.1: LWSP); more than this
// is not padding.
constexpr size_t kMaxPadding = 256;

// RFC 2046 5.1.1 bchars (space allowed, not last).
bool IsBoundaryChar(char c) {
  return absl::ascii_isalnum(static_cast<unsigned char>(c)) ||
         std::string_view("'()+_,-./:=? ").find(c) != std::string_view::npos;
}

// Splits "a; b=c; d=\"e;f\"" at the semicolons outside quotes.
std::vector<std::string_view> SplitParameters(std::string_view value) {
  std::vector<std::string_view> pieces;
  bool quoted = false;
  size_t start = 0;
  for (size_t i = 0; i < value.size(); ++i) {
    const char c = value[i];
    if (quoted && c == '\\') {
      ++i;
    } else if (c == '"') {
      quoted = !quoted;
    } else if (c == ';' && !quoted) {
      pieces.push_back(value.substr(start, i - start));
      start = i + 1;
    }
  }
  pieces.push_back(value.substr(start));
  return pieces;
}

// A parameter's value: a token, or a quoted string (backslash escapes).
std::string Unquote(std::string_view value) {
  value = Strip(value);
  if (value.size() < 2 || value.front() != '"' || value.back() != '"') {
    return std::string(value);
  }
  std::string out;
  for (size_t i = 1; i + 1 < value.size(); ++i) {
    if (value[i] == '\\' && i + 2 < value.size()) ++i;
    out += value[i];
  }
  return out;
}

std::string MediaTypeOf(std::string_view value) {
  const size_t semicolon = value.find(';');
  return absl::AsciiStrToLower(A(Strip(value.substr(0, semicolon))));
}

}  // namespace

absl::StatusOr<StowContentType> ParseStowContentType(
    std::string_view content_type) {
  if (content_type.size() > 1024) {
    return absl::InvalidArgumentError("the Content-Type header is too long");
  }
  const std::vector<std::string_view> pieces = SplitParameters(content_type);
  const std::string media = MediaTypeOf(pieces[0]);
  if (media != "multipart/related") {
    return absl::UnimplementedError(absl::StrCat(
        "STOW-RS takes multipart/related; type=\"application/dicom\", not ",
        media.empty() ? "an empty Content-Type" : media));
  }
  StowContentType result;
  bool has_boundary = false;
  for (size_t i = 1; i < pieces.size(); ++i) {
    const std::string_view piece = Strip(pieces[i]);
    if (piece.empty()) continue;
    const size_t equals = piece.find('=');
    if (equals == std::string_view::npos) {
      return absl::InvalidArgumentError(
          "a Content-Type parameter without a value");
    }
    const std::string name =
        absl::AsciiStrToLower(A(Strip(piece.substr(0, equals))));
    const std::string value = Unquote(piece.substr(equals + 1));
    if (name == "boundary") {
      has_boundary = true;
      result.boundary = value;
    } else if (name == "type") {
      result.type = absl::AsciiStrToLower(value);
    }
  }
  if (!has_boundary) {
    return absl::InvalidArgumentError(
        "multipart/related without a boundary parameter");
  }
  if (result.boundary.empty() || result.boundary.size() > 70 ||
      result.boundary.back() == ' ' ||
      !std::all_of(result.boundary.begin(), result.boundary.end(),
                   IsBoundaryChar)) {
    return absl::InvalidArgumentError(
        "the boundary must be 1-70 characters of RFC 2046's set");
  }
  if (!result.type.empty() && result.type != "application/dicom") {
    return absl::UnimplementedError(
        absl::StrCat("STOW-RS here takes type=\"application/dicom\" (Part 10 "
                     "instances), not type=\"",
                     result.type.substr(0, 64), "\""));
  }
  return result;
}

std::string PartMediaType(const PartHeaders& headers,
                          const std::string& fallback) {
  const auto it = headers.find("content-type");
  if (it == headers.end()) return fallback;
  return MediaTypeOf(it->second);
}

StowBodyParser::StowBodyParser(std::string boundary, StowPartSink* sink,
                               StowBodyLimits limits)
    : delimiter_("\n--" + boundary), sink_(sink), limits_(limits) {
  // The first delimiter may open the body without a line break before it:
  // a line break is assumed there (it is not a byte of the body).
  buffer_ = "\n";
  consumed_ = -1;
}

absl::Status StowBodyParser::Fail(absl::Status status) {
  state_ = State::kFailed;
  buffer_.clear();
  buffer_.shrink_to_fit();
  return status;
}

absl::Status StowBodyParser::Error(std::string_view what) const {
  return absl::InvalidArgumentError(
      absl::StrCat("malformed multipart body at byte ",
                   std::max<int64_t>(consumed_, 0), ": ", A(what)));
}

absl::Status StowBodyParser::Feed(std::string_view bytes) {
  if (state_ == State::kFailed) {
    return absl::FailedPreconditionError("the multipart body already failed");
  }
  if (state_ == State::kEpilogue) return absl::OkStatus();
  buffer_.append(bytes.data(), bytes.size());
  return Run(false);
}

absl::Status StowBodyParser::Finish() {
  if (state_ == State::kFailed) {
    return absl::FailedPreconditionError("the multipart body already failed");
  }
  if (absl::Status s = Run(true); !s.ok()) return s;
  if (state_ != State::kEpilogue) {
    return Fail(Error(
        state_ == State::kPreamble
            ? "no boundary delimiter in the body"
            : "the body ended before the close delimiter (--boundary--)"));
  }
  return absl::OkStatus();
}

absl::Status StowBodyParser::ParseHeaders(std::string_view block) {
  PartHeaders headers;
  std::string name, value;
  int lines = 0;
  auto flush = [&]() -> absl::Status {
    if (name.empty()) return absl::OkStatus();
    headers[name] = std::string(Strip(value));
    name.clear();
    value.clear();
    return absl::OkStatus();
  };
  while (!block.empty()) {
    const size_t newline = block.find('\n');
    std::string_view line = block.substr(0, newline);
    block = newline == std::string_view::npos ? std::string_view()
                                              : block.substr(newline + 1);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    if (line.empty()) continue;
    if (++lines > kMaxHeaderLines) return Error("more than 64 header lines");
    if (line.front() == ' ' || line.front() == '\t') {  // folded (RFC 5322)
      if (name.empty()) return Error("a part header starts with a fold");
      absl::StrAppend(&value, " ", A(Strip(line)));
      continue;
    }
    (void)flush();
    const size_t colon = line.find(':');
    if (colon == std::string_view::npos || colon == 0) {
      return Error("a part header line without a name and a colon");
    }
    const std::string_view raw_name = line.substr(0, colon);
    for (const char c : raw_name) {
      if (c <= ' ' || c >= 127) return Error("a part header name is invalid");
    }
    name = absl::AsciiStrToLower(A(raw_name));
    value = std::string(line.substr(colon + 1));
  }
  (void)flush();
  if (const auto it = headers.find("content-transfer-encoding");
      it != headers.end()) {
    const std::string encoding = absl::AsciiStrToLower(it->second);
    if (encoding != "binary" && encoding != "8bit" && encoding != "7bit") {
      return Error("a part's Content-Transfer-Encoding is not binary");
    }
  }
  if (++parts_ > limits_.max_parts) {
    return Error(absl::StrCat("more than ", limits_.max_parts, " parts"));
  }
  in_part_ = true;
  return sink_->BeginPart(headers);
}

absl::Status StowBodyParser::Run(bool at_end) {
  auto drop = [&](size_t n) {
    buffer_.erase(0, n);
    consumed_ += static_cast<int64_t>(n);
  };
  while (true) {
    switch (state_) {
      case State::kPreamble: {
        const size_t at = buffer_.find(delimiter_);
        if (at == std::string::npos) {
          // Only a delimiter's beginning needs keeping.
          if (buffer_.size() >= delimiter_.size()) {
            drop(buffer_.size() - delimiter_.size() + 1);
          }
          return absl::OkStatus();
        }
        drop(at + delimiter_.size());
        state_ = State::kBoundaryLine;
        break;
      }
      case State::kBoundaryLine: {
        if (buffer_.size() < 2 && !at_end) return absl::OkStatus();
        if (absl::StartsWith(buffer_, "--")) {
          drop(2);
          state_ = State::kEpilogue;
          break;
        }
        size_t i = 0;
        while (i < buffer_.size() && (buffer_[i] == ' ' || buffer_[i] == '\t'))
          ++i;
        if (i > kMaxPadding) return Fail(Error("a boundary line is too long"));
        if (i == buffer_.size() ||
            (buffer_[i] == '\r' && i + 1 == buffer_.size())) {
          return absl::OkStatus();  // at the end: Finish() says so
        }
        size_t line_end = std::string::npos;
        if (buffer_[i] == '\n') line_end = i + 1;
        if (buffer_[i] == '\r' && buffer_[i + 1] == '\n') line_end = i + 2;
        if (line_end == std::string::npos) {
          return Fail(Error("a boundary is followed by other text"));
        }
        drop(line_end);
        state_ = State::kHeaders;
        break;
      }
      case State::kHeaders: {
        size_t end = std::string::npos, body_start = 0;
        if (absl::StartsWith(buffer_, "\r\n")) {
          end = 0;
          body_start = 2;
        } else if (absl::StartsWith(buffer_, "\n")) {
          end = 0;
          body_start = 1;
        } else {
          const size_t lf = buffer_.find("\n\n");
          const size_t crlf = buffer_.find("\n\r\n");
          if (lf != std::string::npos &&
              (crlf == std::string::npos || lf < crlf)) {
            end = lf + 1;
            body_start = lf + 2;
          } else if (crlf != std::string::npos) {
            end = crlf + 1;
            body_start = crlf + 3;
          }
        }
        if (end == std::string::npos) {
          if (static_cast<int64_t>(buffer_.size()) >
              limits_.max_part_header_bytes) {
            return Fail(Error("a part's headers are too long"));
          }
          return absl::OkStatus();  // at the end: Finish() says so
        }
        if (static_cast<int64_t>(end) > limits_.max_part_header_bytes) {
          return Fail(Error("a part's headers are too long"));
        }
        if (absl::Status s =
                ParseHeaders(std::string_view(buffer_).substr(0, end));
            !s.ok()) {
          return Fail(std::move(s));
        }
        drop(body_start);
        state_ = State::kBody;
        break;
      }
      case State::kBody: {
        const size_t at = buffer_.find(delimiter_);
        if (at == std::string::npos) {
          // Keep what may be a delimiter's beginning, and the CR before it.
          if (buffer_.size() > delimiter_.size()) {
            const size_t n = buffer_.size() - delimiter_.size();
            if (absl::Status s =
                    sink_->PartBytes(std::string_view(buffer_).substr(0, n));
                !s.ok()) {
              return Fail(std::move(s));
            }
            drop(n);
          }
          return absl::OkStatus();
        }
        const size_t end = at > 0 && buffer_[at - 1] == '\r' ? at - 1 : at;
        if (end > 0) {
          if (absl::Status s =
                  sink_->PartBytes(std::string_view(buffer_).substr(0, end));
              !s.ok()) {
            return Fail(std::move(s));
          }
        }
        in_part_ = false;
        if (absl::Status s = sink_->EndPart(); !s.ok())
          return Fail(std::move(s));
        drop(at + delimiter_.size());
        state_ = State::kBoundaryLine;
        break;
      }
      case State::kEpilogue:
        consumed_ += static_cast<int64_t>(buffer_.size());
        buffer_.clear();
        return absl::OkStatus();
      case State::kFailed:
        return absl::FailedPreconditionError(
            "the multipart body already failed");
    }
  }
}

}  // namespace interslice::server::dicomweb
