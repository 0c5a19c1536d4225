#include "server/net/grpc/upload_stream.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "core/common/sha256.h"
#include "server/base/log_safe.h"

namespace interslice::server {

UploadStream::UploadStream(const UploadStreamLimits& limits)
    : limits_(limits) {}

UploadStream::~UploadStream() = default;

absl::Status UploadStream::Fail(absl::Status status) {
  error_ = std::move(status);
  hash_.reset();
  return error_;
}

absl::Status UploadStream::CheckHeader(const v1::UploadHeader& header) const {
  // A job that reads its series from a DICOM peer uploads no file.
  const bool pacs = header.spec().has_pacs_source();
  if (pacs && (header.file_count() != 0 || header.total_bytes() != 0)) {
    return absl::InvalidArgumentError(
        "spec.pacs_source reads the series from a DICOM peer: the upload "
        "must carry no files (file_count 0)");
  }
  if (!pacs &&
      (header.file_count() < 1 || header.file_count() > limits_.max_files)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "header.file_count must be between 1 and ", limits_.max_files));
  }
  if (header.total_bytes() < 0) {
    return absl::InvalidArgumentError("header.total_bytes must be >= 0");
  }
  if (header.total_bytes() > limits_.max_upload_bytes) {
    return absl::ResourceExhaustedError(
        absl::StrCat("the upload (", header.total_bytes(),
                     " bytes) exceeds the server's limit of ",
                     limits_.max_upload_bytes, " bytes per job"));
  }
  return absl::OkStatus();
}

// The server never uses client file names as paths (uploads are stored by
// index), but refuses names that no honest client sends, so that no later
// use of them can go wrong: absolute paths, ".." components, control
// characters, invalid UTF-8, overlong names. Empty names are allowed.
absl::Status UploadStream::CheckFileName(const std::string& name) const {
  const auto bad = [&](const char* why) {
    return absl::InvalidArgumentError(
        absl::StrCat("file ", index_, ": file_name ", why));
  };
  if (static_cast<int64_t>(name.size()) > limits_.max_file_name_bytes) {
    return bad("is too long");
  }
  if (!IsLogSafe(name)) {
    return bad("holds control characters or invalid UTF-8");
  }
  if (!name.empty() && name.front() == '/') return bad("must be relative");
  std::string_view rest(name);
  while (!rest.empty()) {
    const size_t slash = rest.find('/');
    const std::string_view part = rest.substr(0, slash);
    if (part == "..") return bad("must not contain '..'");
    if (slash == std::string_view::npos) break;
    rest.remove_prefix(slash + 1);
  }
  return absl::OkStatus();
}

absl::Status UploadStream::Next(const v1::UploadRequest& message,
                                UploadStep* step) {
  *step = UploadStep();
  if (!error_.ok()) return error_;
  if (!has_header_) {
    if (!message.has_header()) {
      return Fail(absl::InvalidArgumentError(
          "the first message of an upload must be the header"));
    }
    if (absl::Status s = CheckHeader(message.header()); !s.ok()) {
      return Fail(std::move(s));
    }
    header_ = message.header();
    has_header_ = true;
    step->header = true;
    return absl::OkStatus();
  }
  if (message.has_header()) {
    return Fail(absl::InvalidArgumentError("the header may be sent only once"));
  }
  if (!message.has_chunk()) {
    return Fail(absl::InvalidArgumentError(
        "an upload message must hold a header or a chunk"));
  }
  const v1::FileChunk& chunk = message.chunk();
  const auto data_size = static_cast<int64_t>(chunk.data().size());
  if (data_size > limits_.max_chunk_bytes) {
    return Fail(absl::InvalidArgumentError(
        absl::StrCat("chunk larger than the server's limit of ",
                     limits_.max_chunk_bytes, " bytes")));
  }
  if (chunk.file_index() != index_ || index_ < 0) {
    // A new file: the previous one must be whole.
    if (!complete_) {
      return Fail(absl::InvalidArgumentError(
          absl::StrCat("file ", index_, " ended after ", written_, " of ",
                       size_, " bytes")));
    }
    if (chunk.file_index() != index_ + 1) {
      return Fail(absl::InvalidArgumentError(absl::StrCat(
          "expected file index ", index_ + 1, ", got ", chunk.file_index())));
    }
    if (chunk.file_index() >= header_.file_count()) {
      return Fail(absl::InvalidArgumentError(absl::StrCat(
          "file index ", chunk.file_index(), " is beyond header.file_count (",
          header_.file_count(), ")")));
    }
    index_ = chunk.file_index();
    if (chunk.file_size() < 0 || chunk.sha256().size() != 32) {
      return Fail(absl::InvalidArgumentError(
          absl::StrCat("file ", index_,
                       ": its first chunk must give file_size >= 0 and a "
                       "32-byte sha256")));
    }
    // received_ <= total_bytes always holds, so this cannot overflow.
    if (chunk.file_size() > header_.total_bytes() - received_) {
      return Fail(absl::InvalidArgumentError(
          "the files are larger than header.total_bytes"));
    }
    if (absl::Status s = CheckFileName(chunk.file_name()); !s.ok()) {
      return Fail(std::move(s));
    }
    name_ = chunk.file_name();
    size_ = chunk.file_size();
    written_ = 0;
    expected_sha_ = chunk.sha256();
    hash_ = std::make_unique<Sha256>();
    complete_ = false;
    step->open_file = true;
  } else {
    // Later chunks may repeat the file's metadata, not change it.
    if ((!chunk.file_name().empty() && chunk.file_name() != name_) ||
        (chunk.file_size() != 0 && chunk.file_size() != size_) ||
        (!chunk.sha256().empty() && chunk.sha256() != expected_sha_)) {
      return Fail(absl::InvalidArgumentError(
          absl::StrCat("file ", index_,
                       ": a later chunk changes its name, size or sha256")));
    }
  }
  if (chunk.offset() != written_) {
    return Fail(absl::InvalidArgumentError(
        absl::StrCat("file ", index_, ": expected offset ", written_, ", got ",
                     chunk.offset())));
  }
  if (data_size > size_ - written_) {
    return Fail(absl::InvalidArgumentError(
        absl::StrCat("file ", index_, ": more data than its file_size")));
  }
  step->file_index = index_;
  step->offset = written_;
  step->data = chunk.data();
  if (complete_) return absl::OkStatus();  // an empty chunk after the end
  hash_->Update(chunk.data());
  written_ += data_size;
  received_ += data_size;
  if (written_ == size_) {
    const std::string sha = hash_->Finish();
    hash_.reset();
    if (sha != expected_sha_) {
      return Fail(absl::InvalidArgumentError(
          absl::StrCat("file ", index_, ": SHA-256 mismatch")));
    }
    complete_ = true;
    step->close_file = true;
  }
  return absl::OkStatus();
}

absl::Status UploadStream::Finish() {
  if (!error_.ok()) return error_;
  if (!has_header_) {
    return Fail(absl::InvalidArgumentError("no upload header received"));
  }
  if (index_ != header_.file_count() - 1 || !complete_ ||
      received_ != header_.total_bytes()) {
    return Fail(absl::InvalidArgumentError(
        absl::StrCat("incomplete upload: ", complete_ ? index_ + 1 : index_,
                     " of ", header_.file_count(), " file(s), ", received_,
                     " of ", header_.total_bytes(), " bytes")));
  }
  return absl::OkStatus();
}

}  // namespace interslice::server
