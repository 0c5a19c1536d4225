#include "server/net/dicomweb/multipart.h"

#include <algorithm>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace interslice::server::dicomweb {
namespace {

// Transport padding after a delimiter (RFC 2046 5.1.1 LWSP): a few spaces
// at most in practice; more is not a multipart body.
constexpr size_t kMaxPadding = 256;

// The media type's parameters (RFC 7231 3.1.1.1): name=value or
// name="quoted value", separated by ';'. Names lower-cased. The first
// element is the type itself, under the name "".
std::vector<std::pair<std::string, std::string>> MediaTypeParts(
    absl::string_view text) {
  std::vector<std::pair<std::string, std::string>> out;
  std::string current;
  bool quoted = false;
  std::vector<std::string> items;
  for (size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (quoted && c == '\\' && i + 1 < text.size()) {
      current.push_back(text[++i]);
    } else if (c == '"') {
      quoted = !quoted;
    } else if (c == ';' && !quoted) {
      items.push_back(std::move(current));
      current.clear();
    } else {
      current.push_back(c);
    }
  }
  items.push_back(std::move(current));
  for (size_t i = 0; i < items.size(); ++i) {
    absl::string_view item = absl::StripAsciiWhitespace(items[i]);
    if (i == 0) {
      out.emplace_back("", absl::AsciiStrToLower(item));
      continue;
    }
    const size_t eq = item.find('=');
    if (eq == absl::string_view::npos) continue;
    out.emplace_back(
        absl::AsciiStrToLower(absl::StripAsciiWhitespace(item.substr(0, eq))),
        std::string(absl::StripAsciiWhitespace(item.substr(eq + 1))));
  }
  return out;
}

}  // namespace

absl::StatusOr<std::string> MultipartBoundary(absl::string_view content_type) {
  const auto parts = MediaTypeParts(content_type);
  if (parts.empty() || parts[0].second != "multipart/related") {
    return absl::InvalidArgumentError(
        "the Content-Type is not multipart/related");
  }
  for (const auto& [name, value] : parts) {
    if (name != "boundary") continue;
    if (value.empty() || value.size() > 70) {
      return absl::InvalidArgumentError(
          "the multipart boundary is empty or longer than 70 characters");
    }
    return value;
  }
  return absl::InvalidArgumentError(
      "the multipart/related Content-Type has no boundary");
}

std::string MultipartRootType(absl::string_view content_type) {
  for (const auto& [name, value] : MediaTypeParts(content_type)) {
    if (name == "type") return absl::AsciiStrToLower(value);
  }
  return "";
}

MultipartParser::MultipartParser(std::string boundary, MultipartLimits limits,
                                 MultipartCallbacks callbacks)
    : delimiter_(absl::StrCat("\r\n--", boundary)),
      limits_(limits),
      callbacks_(std::move(callbacks)),
      // The first delimiter may open the body without a CRLF before it:
      // with one put in front, every delimiter looks the same.
      pending_("\r\n") {}

absl::Status MultipartParser::Fail(absl::Status status) {
  error_ = std::move(status);
  pending_.clear();
  return error_;
}

absl::Status MultipartParser::Feed(absl::string_view data) {
  if (!error_.ok()) return error_;
  // The bytes within the total bound are parsed before the bound is
  // reported, so that the first fault in the body is the one reported
  // however the body was cut into chunks.
  const int64_t allowed = limits_.max_total_bytes - total_bytes_;
  const bool over = static_cast<int64_t>(data.size()) > allowed;
  if (over) {
    data = data.substr(0, static_cast<size_t>(std::max<int64_t>(0, allowed)));
  }
  total_bytes_ += static_cast<int64_t>(data.size());
  if (state_ != State::kDone) {  // after it: the epilogue, ignored
    pending_.append(data.data(), data.size());
    bool progressed = true;
    while (progressed) {
      progressed = false;
      if (absl::Status s = Step(&progressed); !s.ok()) return Fail(s);
    }
  }
  if (over) {
    return Fail(absl::ResourceExhaustedError(
        absl::StrCat("the multipart body is larger than ",
                     limits_.max_total_bytes, " bytes")));
  }
  return absl::OkStatus();
}

absl::Status MultipartParser::EmitData(size_t n) {
  if (n == 0) return absl::OkStatus();
  part_bytes_ += static_cast<int64_t>(n);
  // The declared length first: it is within max_part_bytes, so a part that
  // lies is found as such however its data was chunked.
  if (part_declared_length_ >= 0 && part_bytes_ > part_declared_length_) {
    return absl::InvalidArgumentError(
        absl::StrCat("part ", parts_, " is longer than its Content-Length (",
                     part_declared_length_, " bytes)"));
  }
  if (part_bytes_ > limits_.max_part_bytes) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "part ", parts_, " is larger than ", limits_.max_part_bytes, " bytes"));
  }
  if (callbacks_.on_part_data) {
    if (absl::Status s =
            callbacks_.on_part_data(absl::string_view(pending_.data(), n));
        !s.ok()) {
      return s;
    }
  }
  pending_.erase(0, n);
  return absl::OkStatus();
}

absl::Status MultipartParser::EndPart() {
  if (part_declared_length_ >= 0 && part_bytes_ != part_declared_length_) {
    return absl::InvalidArgumentError(absl::StrCat(
        "part ", parts_, " has ", part_bytes_,
        " bytes but its Content-Length says ", part_declared_length_));
  }
  return callbacks_.on_part_end ? callbacks_.on_part_end() : absl::OkStatus();
}

absl::Status MultipartParser::Step(bool* progressed) {
  switch (state_) {
    case State::kPreamble: {
      const size_t at = pending_.find(delimiter_);
      if (at == std::string::npos) {
        // Keep what could be the start of a delimiter.
        if (pending_.size() >= delimiter_.size()) {
          pending_.erase(0, pending_.size() - (delimiter_.size() - 1));
        }
        return absl::OkStatus();
      }
      pending_.erase(0, at + delimiter_.size());
      state_ = State::kAfterDelimiter;
      *progressed = true;
      return absl::OkStatus();
    }
    case State::kAfterDelimiter: {
      size_t padding = 0;
      while (padding < pending_.size() &&
             (pending_[padding] == ' ' || pending_[padding] == '\t')) {
        ++padding;
      }
      if (padding > kMaxPadding) {
        return absl::InvalidArgumentError(
            "malformed multipart body: a boundary line goes on with spaces");
      }
      if (padding == 0 && pending_.size() >= 2 && pending_[0] == '-' &&
          pending_[1] == '-') {
        state_ = State::kDone;  // the close delimiter; the rest is epilogue
        pending_.clear();
        *progressed = true;
        return absl::OkStatus();
      }
      if (pending_.size() < padding + 2) return absl::OkStatus();  // more
      if (pending_[padding] != '\r' || pending_[padding + 1] != '\n') {
        return absl::InvalidArgumentError(
            "malformed multipart body: a boundary is followed by other "
            "text");
      }
      pending_.erase(0, padding + 2);
      state_ = State::kHeaders;
      *progressed = true;
      return absl::OkStatus();
    }
    case State::kHeaders: {
      size_t end = std::string::npos;
      size_t skip = 0;
      if (pending_.size() >= 2 && pending_[0] == '\r' && pending_[1] == '\n') {
        end = 0;  // no headers at all
        skip = 2;
      } else {
        end = pending_.find("\r\n\r\n");
        skip = 4;
      }
      if (end == std::string::npos) {
        // Up to 3 bytes of the blank line's CRLFs may be here already.
        if (pending_.size() > limits_.max_header_bytes + 3) {
          return absl::ResourceExhaustedError(
              absl::StrCat("a part's headers are longer than ",
                           limits_.max_header_bytes, " bytes"));
        }
        return absl::OkStatus();
      }
      if (end > limits_.max_header_bytes) {
        return absl::ResourceExhaustedError(
            absl::StrCat("a part's headers are longer than ",
                         limits_.max_header_bytes, " bytes"));
      }
      ++parts_;
      if (parts_ > limits_.max_parts) {
        return absl::ResourceExhaustedError(absl::StrCat(
            "the multipart body has more than ", limits_.max_parts, " parts"));
      }
      std::map<std::string, std::string> headers;
      part_declared_length_ = -1;
      if (end > 0) {
        for (absl::string_view line :
             absl::StrSplit(absl::string_view(pending_.data(), end), "\r\n")) {
          const size_t colon = line.find(':');
          if (colon == absl::string_view::npos) {
            return absl::InvalidArgumentError(
                absl::StrCat("malformed multipart body: a header line of part ",
                             parts_, " has no colon"));
          }
          std::string name = absl::AsciiStrToLower(
              absl::StripAsciiWhitespace(line.substr(0, colon)));
          std::string value(absl::StripAsciiWhitespace(line.substr(colon + 1)));
          if (name == "content-length") {
            int64_t length = -1;
            if (!absl::SimpleAtoi(value, &length) || length < 0) {
              return absl::InvalidArgumentError(
                  absl::StrCat("part ", parts_,
                               " has a Content-Length that is not a "
                               "number"));
            }
            if (length > limits_.max_part_bytes) {
              return absl::ResourceExhaustedError(absl::StrCat(
                  "part ", parts_, " announces ", length,
                  " bytes, more than the limit of ", limits_.max_part_bytes));
            }
            part_declared_length_ = length;
          }
          headers[std::move(name)] = std::move(value);
        }
      }
      pending_.erase(0, end + skip);
      part_bytes_ = 0;
      state_ = State::kBody;
      *progressed = true;
      if (callbacks_.on_part_begin) return callbacks_.on_part_begin(headers);
      return absl::OkStatus();
    }
    case State::kBody: {
      const size_t at = pending_.find(delimiter_);
      if (at == std::string::npos) {
        if (pending_.size() >= delimiter_.size()) {
          return EmitData(pending_.size() - (delimiter_.size() - 1));
        }
        return absl::OkStatus();
      }
      if (absl::Status s = EmitData(at); !s.ok()) return s;
      pending_.erase(0, delimiter_.size());
      state_ = State::kAfterDelimiter;
      *progressed = true;
      return EndPart();
    }
    case State::kDone:
      pending_.clear();
      return absl::OkStatus();
  }
  return absl::OkStatus();
}

absl::Status MultipartParser::Finish() {
  if (!error_.ok()) return error_;
  switch (state_) {
    case State::kDone:
      return absl::OkStatus();
    case State::kPreamble:
      return Fail(absl::InvalidArgumentError(
          "no multipart boundary found in the body"));
    default:
      return Fail(absl::InvalidArgumentError(
          absl::StrCat("the multipart body is truncated: it ends in part ",
                       parts_, " without the closing boundary")));
  }
}

}  // namespace interslice::server::dicomweb
