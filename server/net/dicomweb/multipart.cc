#include "server/net/dicomweb/multipart.h"

#include <algorithm>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace interslice::server::dicomweb {
namespace {

// Debian's abseil has its own string_view type.
absl::string_view AbslView(std::string_view v) { return {v.data(), v.size()}; }
std::string_view StripView(std::string_view v) {
  const absl::string_view s = absl::StripAsciiWhitespace(AbslView(v));
  return {s.data(), s.size()};
}

// Transport padding after a delimiter (RFC 2046 5.1.1 LWSP): a few spaces
// at most in practice; more is not a multipart body.
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
  value = StripView(value);
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

// One piece of SplitParameters with every quote removed wherever it is and
// backslash escapes inside quotes resolved (the lenient reading of
// MediaTypeParts).
std::string Dequote(std::string_view piece) {
  std::string out;
  bool quoted = false;
  for (size_t i = 0; i < piece.size(); ++i) {
    const char c = piece[i];
    if (quoted && c == '\\' && i + 1 < piece.size()) {
      out.push_back(piece[++i]);
    } else if (c == '"') {
      quoted = !quoted;
    } else {
      out.push_back(c);
    }
  }
  return out;
}

// The media type's parameters (RFC 7231 3.1.1.1): name=value or
// name="quoted value", separated by ';'. Names lower-cased. The first
// element is the type itself, under the name "".
std::vector<std::pair<std::string, std::string>> MediaTypeParts(
    std::string_view text) {
  std::vector<std::pair<std::string, std::string>> out;
  const std::vector<std::string_view> pieces = SplitParameters(text);
  for (size_t i = 0; i < pieces.size(); ++i) {
    const std::string item_text = Dequote(pieces[i]);
    const std::string_view item = StripView(item_text);
    if (i == 0) {
      out.emplace_back("", absl::AsciiStrToLower(AbslView(item)));
      continue;
    }
    const size_t eq = item.find('=');
    if (eq == std::string_view::npos) continue;
    out.emplace_back(
        absl::AsciiStrToLower(AbslView(StripView(item.substr(0, eq)))),
        std::string(StripView(item.substr(eq + 1))));
  }
  return out;
}

std::string MediaTypeOf(std::string_view value) {
  const size_t semicolon = value.find(';');
  return absl::AsciiStrToLower(AbslView(StripView(value.substr(0, semicolon))));
}

}  // namespace

MultipartOptions WadoResponseMultipart(const MultipartLimits& limits) {
  MultipartOptions options;
  options.limits = limits;
  return options;
}

MultipartOptions StowRequestMultipart(int64_t max_parts) {
  MultipartOptions options;
  options.line_breaks = MultipartLineBreaks::kCrlfOrLf;
  options.header_syntax = MultipartHeaderSyntax::kFolded;
  options.check_content_length = false;
  options.check_transfer_encoding = true;
  options.errors = MultipartErrors::kAtByteOffset;
  options.limits.max_part_bytes = kMultipartUnbounded;
  options.limits.max_total_bytes = kMultipartUnbounded;
  options.limits.max_parts = max_parts;
  options.limits.max_header_bytes = 16 * 1024;
  options.limits.max_header_lines = 64;
  return options;
}

MultipartParser::MultipartParser(std::string_view boundary,
                                 const MultipartOptions& options,
                                 MultipartSink* sink)
    : options_(options),
      lenient_(options.line_breaks == MultipartLineBreaks::kCrlfOrLf),
      delimiter_(
          absl::StrCat(lenient_ ? "\n--" : "\r\n--", AbslView(boundary))),
      sink_(sink),
      // The first delimiter may open the body without a line break before
      // it: with one put in front (not a byte of the body), every delimiter
      // looks the same.
      pending_(lenient_ ? "\n" : "\r\n"),
      consumed_(-static_cast<int64_t>(pending_.size())) {}

absl::Status MultipartParser::Error(Fault fault, std::string_view what) const {
  if (options_.errors == MultipartErrors::kAtByteOffset) {
    return absl::InvalidArgumentError(
        absl::StrCat("malformed multipart body at byte ",
                     std::max<int64_t>(consumed_, 0), ": ", AbslView(what)));
  }
  if (fault == Fault::kLimit) {
    return absl::ResourceExhaustedError(AbslView(what));
  }
  return absl::InvalidArgumentError(
      absl::StrCat("malformed multipart body: ", AbslView(what)));
}

absl::Status MultipartParser::Fail(absl::Status status) {
  error_ = std::move(status);
  pending_.clear();
  pending_.shrink_to_fit();
  return error_;
}

void MultipartParser::Drop(size_t n) {
  pending_.erase(0, n);
  consumed_ += static_cast<int64_t>(n);
}

absl::Status MultipartParser::Feed(std::string_view bytes) {
  if (!error_.ok()) return error_;
  // The bytes within the total bound are parsed before the bound is
  // reported, so that the first fault in the body is the one reported
  // however the body was cut into pieces.
  const int64_t allowed = options_.limits.max_total_bytes - total_bytes_;
  const bool over = static_cast<int64_t>(bytes.size()) > allowed;
  if (over) {
    bytes = bytes.substr(0, static_cast<size_t>(std::max<int64_t>(0, allowed)));
  }
  total_bytes_ += static_cast<int64_t>(bytes.size());
  if (state_ == State::kDone) {
    consumed_ += static_cast<int64_t>(bytes.size());  // the epilogue
  } else {
    pending_.append(bytes.data(), bytes.size());
    bool progressed = true;
    while (progressed) {
      progressed = false;
      if (absl::Status s = Step(&progressed); !s.ok()) return Fail(s);
    }
  }
  if (over) {
    return Fail(Error(Fault::kLimit,
                      absl::StrCat("the multipart body is larger than ",
                                   options_.limits.max_total_bytes, " bytes")));
  }
  return absl::OkStatus();
}

absl::Status MultipartParser::Finish() {
  if (!error_.ok()) return error_;
  switch (state_) {
    case State::kDone:
      return absl::OkStatus();
    case State::kPreamble:
      return Fail(Error(Fault::kMalformed,
                        "no multipart boundary delimiter in the body"));
    default:
      return Fail(
          Error(Fault::kMalformed,
                absl::StrCat("the body is truncated: it ends in part ", parts_,
                             " without the close delimiter (--boundary--)")));
  }
}

absl::Status MultipartParser::Step(bool* progressed) {
  switch (state_) {
    case State::kPreamble: {
      const size_t at = pending_.find(delimiter_);
      if (at == std::string::npos) {
        // Keep what could be the start of a delimiter.
        if (pending_.size() >= delimiter_.size()) {
          Drop(pending_.size() - (delimiter_.size() - 1));
        }
        return absl::OkStatus();
      }
      Drop(at + delimiter_.size());
      state_ = State::kBoundaryLine;
      *progressed = true;
      return absl::OkStatus();
    }
    case State::kBoundaryLine:
      return StepBoundaryLine(progressed);
    case State::kHeaders:
      return StepHeaders(progressed);
    case State::kBody:
      return StepBody(progressed);
    case State::kDone:
      Drop(pending_.size());  // the epilogue
      return absl::OkStatus();
  }
  return absl::OkStatus();
}

// After a delimiter: "--" (the close delimiter), or transport padding and a
// line break (the next part's headers follow).
absl::Status MultipartParser::StepBoundaryLine(bool* progressed) {
  size_t padding = 0;
  while (padding < pending_.size() &&
         (pending_[padding] == ' ' || pending_[padding] == '\t')) {
    ++padding;
  }
  if (padding > kMaxPadding) {
    return Error(Fault::kMalformed, "a boundary line goes on with spaces");
  }
  if (padding == pending_.size()) return absl::OkStatus();  // more
  if (padding == 0 && pending_[0] == '-') {
    if (pending_.size() < 2) return absl::OkStatus();  // more
    if (pending_[1] == '-') {
      Drop(pending_.size());  // the close delimiter; the rest is epilogue
      state_ = State::kDone;
      *progressed = true;
      return absl::OkStatus();
    }
  }
  // With CRLF only, the line is judged when its two bytes are here (a body
  // that ends earlier is truncated, whatever the one byte is).
  if (!lenient_ && pending_.size() < padding + 2) return absl::OkStatus();
  size_t line_end = std::string::npos;
  if (pending_[padding] == '\r') {
    if (pending_.size() < padding + 2) return absl::OkStatus();  // more
    if (pending_[padding + 1] == '\n') line_end = padding + 2;
  } else if (pending_[padding] == '\n' && lenient_) {
    line_end = padding + 1;
  }
  if (line_end == std::string::npos) {
    return Error(Fault::kMalformed, "a boundary is followed by other text");
  }
  Drop(line_end);
  state_ = State::kHeaders;
  *progressed = true;
  return absl::OkStatus();
}

absl::Status MultipartParser::StepHeaders(bool* progressed) {
  // The header lines with their line breaks, then the empty line.
  size_t lines_end = std::string::npos;
  size_t body_start = 0;
  if (absl::StartsWith(pending_, "\r\n")) {
    lines_end = 0;  // no headers at all
    body_start = 2;
  } else if (lenient_ && absl::StartsWith(pending_, "\n")) {
    lines_end = 0;
    body_start = 1;
  } else if (!lenient_) {
    if (const size_t at = pending_.find("\r\n\r\n"); at != std::string::npos) {
      lines_end = at + 2;
      body_start = at + 4;
    }
  } else {
    const size_t lf = pending_.find("\n\n");
    const size_t crlf = pending_.find("\n\r\n");
    if (lf != std::string::npos && (crlf == std::string::npos || lf < crlf)) {
      lines_end = lf + 1;
      body_start = lf + 2;
    } else if (crlf != std::string::npos) {
      lines_end = crlf + 1;
      body_start = crlf + 3;
    }
  }
  const int64_t max_bytes = options_.limits.max_header_bytes;
  // While the empty line is not whole, its CR may be here already: more
  // than one byte past the bound is past it whatever comes next.
  if (lines_end == std::string::npos
          ? static_cast<int64_t>(pending_.size()) > max_bytes + 1
          : static_cast<int64_t>(lines_end) > max_bytes) {
    return Error(Fault::kLimit,
                 absl::StrCat("a part's headers are too long (more than ",
                              max_bytes, " bytes)"));
  }
  if (lines_end == std::string::npos) return absl::OkStatus();  // more
  ++parts_;
  if (parts_ > options_.limits.max_parts) {
    return Error(Fault::kLimit,
                 absl::StrCat("the multipart body has more than ",
                              options_.limits.max_parts, " parts"));
  }
  PartHeaders headers;
  part_declared_length_ = -1;
  if (absl::Status s = ParseHeaderLines(
          std::string_view(pending_).substr(0, lines_end), &headers);
      !s.ok()) {
    return s;
  }
  if (options_.check_transfer_encoding) {
    if (const auto it = headers.find("content-transfer-encoding");
        it != headers.end()) {
      const std::string encoding = absl::AsciiStrToLower(it->second);
      if (encoding != "binary" && encoding != "8bit" && encoding != "7bit") {
        return Error(Fault::kMalformed,
                     "a part's Content-Transfer-Encoding is not binary");
      }
    }
  }
  Drop(body_start);
  part_bytes_ = 0;
  state_ = State::kBody;
  *progressed = true;
  return sink_->BeginPart(headers);
}

absl::Status MultipartParser::ParseHeaderLines(std::string_view block,
                                               PartHeaders* headers) {
  const bool folded = options_.header_syntax == MultipartHeaderSyntax::kFolded;
  // The header being read: kFolded continues it on the lines that follow.
  bool open = false;
  std::string name, value;
  int lines = 0;
  while (!block.empty()) {
    std::string_view line;
    if (lenient_) {
      const size_t lf = block.find('\n');
      line = block.substr(0, lf);
      block = lf == std::string_view::npos ? std::string_view()
                                           : block.substr(lf + 1);
      if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    } else {
      const size_t crlf = block.find("\r\n");
      line = block.substr(0, crlf);
      block = crlf == std::string_view::npos ? std::string_view()
                                             : block.substr(crlf + 2);
    }
    if (line.empty()) continue;
    if (options_.limits.max_header_lines > 0 &&
        ++lines > options_.limits.max_header_lines) {
      return Error(Fault::kLimit,
                   absl::StrCat("more than ", options_.limits.max_header_lines,
                                " header lines"));
    }
    if (folded && (line.front() == ' ' || line.front() == '\t')) {  // RFC 5322
      if (!open) {
        return Error(Fault::kMalformed, "a part header starts with a fold");
      }
      absl::StrAppend(&value, " ", AbslView(StripView(line)));
      continue;
    }
    if (open) {
      if (absl::Status s = AddHeader(std::move(name), value, headers);
          !s.ok()) {
        return s;
      }
      open = false;
    }
    const size_t colon = line.find(':');
    if (colon == std::string_view::npos) {
      return Error(Fault::kMalformed, absl::StrCat("a header line of part ",
                                                   parts_, " has no colon"));
    }
    std::string_view raw_name = line.substr(0, colon);
    if (folded) {
      if (raw_name.empty()) {
        return Error(Fault::kMalformed, absl::StrCat("a header line of part ",
                                                     parts_, " has no name"));
      }
      for (const char c : raw_name) {
        if (c <= ' ' || c >= 127) {
          return Error(Fault::kMalformed, "a part header name is invalid");
        }
      }
    } else {
      raw_name = StripView(raw_name);
    }
    name = absl::AsciiStrToLower(AbslView(raw_name));
    value = std::string(line.substr(colon + 1));
    open = true;
  }
  if (open) return AddHeader(std::move(name), value, headers);
  return absl::OkStatus();
}

absl::Status MultipartParser::AddHeader(std::string name,
                                        std::string_view value,
                                        PartHeaders* headers) {
  value = StripView(value);
  if (options_.check_content_length && name == "content-length") {
    int64_t length = -1;
    if (!absl::SimpleAtoi(AbslView(value), &length) || length < 0) {
      return Error(Fault::kMalformed,
                   absl::StrCat("part ", parts_,
                                " has a Content-Length that is not a number"));
    }
    if (length > options_.limits.max_part_bytes) {
      return Error(Fault::kLimit,
                   absl::StrCat("part ", parts_, " announces ", length,
                                " bytes, more than the limit of ",
                                options_.limits.max_part_bytes));
    }
    part_declared_length_ = length;
  }
  (*headers)[std::move(name)] = std::string(value);
  return absl::OkStatus();
}

absl::Status MultipartParser::StepBody(bool* progressed) {
  const size_t at = pending_.find(delimiter_);
  if (at == std::string::npos) {
    // Keep what could be the start of a delimiter, and with bare LFs the CR
    // that may come before it.
    const size_t hold = delimiter_.size() - (lenient_ ? 0 : 1);
    if (pending_.size() > hold) return EmitData(pending_.size() - hold);
    return absl::OkStatus();
  }
  // A CR before a bare-LF delimiter is the delimiter's (a CRLF).
  const size_t end =
      lenient_ && at > 0 && pending_[at - 1] == '\r' ? at - 1 : at;
  if (absl::Status s = EmitData(end); !s.ok()) return s;
  Drop(at - end + delimiter_.size());
  state_ = State::kBoundaryLine;
  *progressed = true;
  return EndPart();
}

absl::Status MultipartParser::EmitData(size_t n) {
  if (n == 0) return absl::OkStatus();
  part_bytes_ += static_cast<int64_t>(n);
  // The declared length first: it is within max_part_bytes, so a part that
  // lies is found as such however its data was chunked.
  if (part_declared_length_ >= 0 && part_bytes_ > part_declared_length_) {
    return Error(
        Fault::kMalformed,
        absl::StrCat("part ", parts_, " is longer than its Content-Length (",
                     part_declared_length_, " bytes)"));
  }
  if (part_bytes_ > options_.limits.max_part_bytes) {
    return Error(Fault::kLimit,
                 absl::StrCat("part ", parts_, " is larger than ",
                              options_.limits.max_part_bytes, " bytes"));
  }
  if (absl::Status s = sink_->PartBytes(std::string_view(pending_.data(), n));
      !s.ok()) {
    return s;
  }
  Drop(n);
  return absl::OkStatus();
}

absl::Status MultipartParser::EndPart() {
  if (part_declared_length_ >= 0 && part_bytes_ != part_declared_length_) {
    return Error(Fault::kMalformed,
                 absl::StrCat("part ", parts_, " has ", part_bytes_,
                              " bytes but its Content-Length says ",
                              part_declared_length_));
  }
  return sink_->EndPart();
}

absl::StatusOr<std::string> MultipartBoundary(absl::string_view content_type) {
  const auto parts = MediaTypeParts(
      std::string_view(content_type.data(), content_type.size()));
  if (parts.empty() || parts[0].second != "multipart/related") {
    return absl::InvalidArgumentError(
        "the Content-Type is not multipart/related");
  }
  for (const auto& [name, value] : parts) {
    if (name != "boundary") continue;
    if (value.empty() || value.size() > kMaxBoundaryChars) {
      return absl::InvalidArgumentError(
          absl::StrCat("the multipart boundary is empty or longer than ",
                       kMaxBoundaryChars, " characters"));
    }
    return value;
  }
  return absl::InvalidArgumentError(
      "the multipart/related Content-Type has no boundary");
}

std::string MultipartRootType(absl::string_view content_type) {
  for (const auto& [name, value] : MediaTypeParts(
           std::string_view(content_type.data(), content_type.size()))) {
    if (name == "type") return absl::AsciiStrToLower(value);
  }
  return "";
}

absl::StatusOr<StowContentType> ParseStowContentType(
    std::string_view content_type) {
  if (content_type.size() > 1024) {
    return absl::InvalidArgumentError("the Content-Type header is too long");
  }
  const std::vector<std::string_view> pieces = SplitParameters(content_type);
  const std::string media = MediaTypeOf(pieces[0]);
  StowContentType result;
  if (media == "application/dicom") {
    result.single_part = true;
    result.type = media;
    return result;
  }
  if (media != "multipart/related") {
    return absl::UnimplementedError(absl::StrCat(
        "STOW-RS takes multipart/related; type=\"application/dicom\" (or "
        "one instance as application/dicom), not ",
        media.empty() ? "an empty Content-Type" : media));
  }
  bool has_boundary = false;
  for (size_t i = 1; i < pieces.size(); ++i) {
    const std::string_view piece = StripView(pieces[i]);
    if (piece.empty()) continue;
    const size_t equals = piece.find('=');
    if (equals == std::string_view::npos) {
      return absl::InvalidArgumentError(
          "a Content-Type parameter without a value");
    }
    const std::string name =
        absl::AsciiStrToLower(AbslView(StripView(piece.substr(0, equals))));
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
  if (result.boundary.empty() || result.boundary.size() > kMaxBoundaryChars ||
      result.boundary.back() == ' ' ||
      !std::all_of(result.boundary.begin(), result.boundary.end(),
                   IsBoundaryChar)) {
    return absl::InvalidArgumentError(
        absl::StrCat("the boundary must be 1-", kMaxBoundaryChars,
                     " characters of RFC 2046's set"));
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

}  // namespace interslice::server::dicomweb
