#include "server/node/dataset_scan.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <array>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

#include "absl/strings/str_cat.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dctag.h"
#include "dcmtk/dcmdata/dcxfer.h"

namespace interslice::server::node {
namespace {

constexpr uint64_t kUndefined = 0xFFFFFFFFu;
constexpr uint64_t kNoEnd = std::numeric_limits<uint64_t>::max();

// Bytes in order, with skipping; Size() is the total when known (files,
// memory), else kNoEnd (an inflating stream).
class ByteSource {
 public:
  virtual ~ByteSource() = default;
  // Exactly n bytes, or false (end of data or a read error).
  virtual bool Read(void* out, size_t n) = 0;
  virtual bool Skip(uint64_t n) = 0;
  // The next n (<= 8) bytes without consuming them.
  virtual bool Peek(void* out, size_t n) = 0;
  virtual bool AtEnd() = 0;
  virtual uint64_t Position() const = 0;
  virtual uint64_t Size() const = 0;
  // Set when the source failed for a reason other than the data (I/O).
  virtual const char* error() const { return nullptr; }
};

class MemorySource : public ByteSource {
 public:
  explicit MemorySource(std::string_view bytes) : bytes_(bytes) {}
  bool Read(void* out, size_t n) override {
    if (n > bytes_.size() - pos_) return false;
    std::memcpy(out, bytes_.data() + pos_, n);
    pos_ += n;
    return true;
  }
  bool Skip(uint64_t n) override {
    if (n > bytes_.size() - pos_) return false;
    pos_ += n;
    return true;
  }
  bool Peek(void* out, size_t n) override {
    if (n > bytes_.size() - pos_) return false;
    std::memcpy(out, bytes_.data() + pos_, n);
    return true;
  }
  bool AtEnd() override { return pos_ == bytes_.size(); }
  uint64_t Position() const override { return pos_; }
  uint64_t Size() const override { return bytes_.size(); }

 private:
  std::string_view bytes_;
  uint64_t pos_ = 0;
};

// A file read through a buffer with pread; skipping moves the offset only,
// so pixel data is never read.
class FileSource : public ByteSource {
 public:
  FileSource(int fd, uint64_t size, uint64_t start)
      : fd_(fd), size_(size), pos_(start) {}
  bool Read(void* out, size_t n) override {
    auto* dst = static_cast<unsigned char*>(out);
    while (n > 0) {
      if (pos_ >= buffer_start_ + buffer_.size() || pos_ < buffer_start_) {
        if (!Fill()) return false;
      }
      const size_t offset = static_cast<size_t>(pos_ - buffer_start_);
      const size_t take = std::min(n, buffer_.size() - offset);
      std::memcpy(dst, buffer_.data() + offset, take);
      dst += take;
      n -= take;
      pos_ += take;
    }
    return true;
  }
  bool Skip(uint64_t n) override {
    if (n > size_ - pos_) return false;
    pos_ += n;
    return true;
  }
  bool Peek(void* out, size_t n) override {
    const uint64_t at = pos_;
    const bool ok = Read(out, n);
    pos_ = at;
    return ok;
  }
  bool AtEnd() override { return pos_ >= size_; }
  uint64_t Position() const override { return pos_; }
  uint64_t Size() const override { return size_; }
  const char* error() const override { return error_; }

 private:
  bool Fill() {
    if (pos_ >= size_) return false;
    const size_t want =
        static_cast<size_t>(std::min<uint64_t>(kBuffer, size_ - pos_));
    buffer_.resize(want);
    size_t got = 0;
    while (got < want) {
      const ssize_t r = ::pread(fd_, buffer_.data() + got, want - got,
                                static_cast<off_t>(pos_ + got));
      if (r < 0 && errno == EINTR) continue;
      if (r <= 0) {
        error_ = "the file cannot be read";
        buffer_.clear();
        return false;
      }
      got += static_cast<size_t>(r);
    }
    buffer_start_ = pos_;
    return true;
  }
  static constexpr uint64_t kBuffer = 64 * 1024;
  int fd_;
  uint64_t size_;
  uint64_t pos_;
  std::vector<unsigned char> buffer_;
  uint64_t buffer_start_ = 0;
  const char* error_ = nullptr;
};

// The inflated bytes of a deflated data set (PS3.5 A.5: raw deflate,
// RFC 1951) read from `in`, at most `max_bytes` of them.
class InflateSource : public ByteSource {
 public:
  InflateSource(ByteSource* in, uint64_t max_bytes)
      : in_(in), max_bytes_(max_bytes) {
    std::memset(&z_, 0, sizeof(z_));
    ok_ = inflateInit2(&z_, -MAX_WBITS) == Z_OK;
    if (!ok_) error_ = "zlib cannot be initialised";
  }
  ~InflateSource() override {
    if (ok_) inflateEnd(&z_);
  }
  bool Read(void* out, size_t n) override {
    auto* dst = static_cast<unsigned char*>(out);
    while (n > 0) {
      if (out_pos_ == out_.size() && !Fill()) return false;
      const size_t take = std::min(n, out_.size() - out_pos_);
      if (dst != nullptr) {
        std::memcpy(dst, out_.data() + out_pos_, take);
        dst += take;
      }
      out_pos_ += take;
      pos_ += take;
      n -= take;
    }
    return true;
  }
  bool Skip(uint64_t n) override {
    while (n > 0) {
      if (out_pos_ == out_.size() && !Fill()) return false;
      const uint64_t take = std::min<uint64_t>(n, out_.size() - out_pos_);
      out_pos_ += static_cast<size_t>(take);
      pos_ += take;
      n -= take;
    }
    return true;
  }
  bool Peek(void* out, size_t n) override {
    while (out_.size() - out_pos_ < n) {
      std::vector<unsigned char> tail(out_.begin() + out_pos_, out_.end());
      const bool more = Fill();
      if (more) {
        out_.insert(out_.begin(), tail.begin(), tail.end());
      } else {
        out_ = std::move(tail);
      }
      out_pos_ = 0;
      if (!more) return false;
    }
    std::memcpy(out, out_.data() + out_pos_, n);
    return true;
  }
  // The end only when the stream ended well: after a data error, a stream
  // cut short or the size limit, the next Read fails and says why.
  bool AtEnd() override {
    if (out_pos_ < out_.size()) return false;
    if (Fill()) return false;
    return !bad_data_ && !too_large_ && !truncated_;
  }
  uint64_t Position() const override { return pos_; }
  uint64_t Size() const override { return kNoEnd; }
  const char* error() const override { return error_; }

  bool too_large() const { return too_large_; }
  bool bad_data() const { return bad_data_; }
  bool truncated() const { return truncated_; }

 private:
  // Inflates the next bytes. As DCMTK's reader does (dcistrmz.cc), a zero
  // byte follows the input (raw deflate may need it to finish), and what
  // inflate produced before a data error is handed out first: the scan sees
  // every byte DCMTK's parser would, then fails at the error.
  bool Fill() {
    if (!ok_ || finished_ || failed_) return false;
    out_.resize(kChunk);
    out_pos_ = 0;
    while (true) {
      if (z_.avail_in == 0) {
        if (!in_->AtEnd()) {
          const uint64_t left = in_->Size() - in_->Position();
          const size_t take =
              static_cast<size_t>(std::min<uint64_t>(kChunk, left));
          in_buffer_.resize(take);
          if (!in_->Read(in_buffer_.data(), take)) {
            error_ = "the deflated data cannot be read";
            failed_ = true;
            return false;
          }
          z_.next_in = in_buffer_.data();
          z_.avail_in = static_cast<uInt>(take);
        } else if (!padded_) {
          padded_ = true;
          z_.next_in = &pad_;
          z_.avail_in = 1;
        }
      }
      z_.next_out = out_.data();
      z_.avail_out = static_cast<uInt>(out_.size());
      const uInt input_before = z_.avail_in;
      const int rc = inflate(&z_, Z_NO_FLUSH);
      const size_t produced = out_.size() - z_.avail_out;
      if (rc == Z_STREAM_END) {
        finished_ = true;
      } else if (rc != Z_OK && !(rc == Z_BUF_ERROR && input_before == 0)) {
        // Z_DATA_ERROR and the like; Z_BUF_ERROR with input left means no
        // progress is possible either.
        bad_data_ = true;
        failed_ = true;
      }
      if (produced > 0) {
        total_ += produced;
        if (total_ > max_bytes_) {
          too_large_ = true;
          failed_ = true;
          out_.clear();
          return false;
        }
        out_.resize(produced);
        return true;
      }
      if (finished_ || failed_) return false;
      if (z_.avail_in == 0 && in_->AtEnd() && padded_) {
        // The input is used up and the stream never ended.
        truncated_ = true;
        failed_ = true;
        return false;
      }
    }
  }

  static constexpr size_t kChunk = 64 * 1024;
  ByteSource* in_;
  uint64_t max_bytes_;
  z_stream z_;
  bool ok_ = false;
  bool finished_ = false;
  bool failed_ = false;
  bool too_large_ = false;
  bool bad_data_ = false;
  bool truncated_ = false;
  bool padded_ = false;
  unsigned char pad_ = 0;
  std::vector<unsigned char> in_buffer_;
  std::vector<unsigned char> out_;
  size_t out_pos_ = 0;
  uint64_t pos_ = 0;
  uint64_t total_ = 0;
  const char* error_ = nullptr;
};

struct Encoding {
  bool explicit_vr = true;
  bool big_endian = false;
};

uint16_t U16(const unsigned char* b, bool big) {
  return big ? static_cast<uint16_t>((b[0] << 8) | b[1])
             : static_cast<uint16_t>(b[0] | (b[1] << 8));
}
uint32_t U32(const unsigned char* b, bool big) {
  return big ? (uint32_t{b[0]} << 24) | (uint32_t{b[1]} << 16) |
                   (uint32_t{b[2]} << 8) | b[3]
             : uint32_t{b[0]} | (uint32_t{b[1]} << 8) | (uint32_t{b[2]} << 16) |
                   (uint32_t{b[3]} << 24);
}

// The VRs of PS3.5 table 6.2-1, and which of them have the 4-byte length
// form in explicit VR (PS3.5 7.1.2).
bool KnownVr(char a, char b, bool* long_form) {
  static constexpr std::array<const char*, 21> kShort = {
      "AE", "AS", "AT", "CS", "DA", "DS", "DT", "FL", "FD", "IS", "LO",
      "LT", "PN", "SH", "SL", "SS", "ST", "TM", "UI", "UL", "US"};
  static constexpr std::array<const char*, 13> kLong = {
      "OB", "OD", "OF", "OL", "OV", "OW", "SQ",
      "SV", "UC", "UN", "UR", "UT", "UV"};
  for (const char* vr : kLong) {
    if (vr[0] == a && vr[1] == b) {
      *long_form = true;
      return true;
    }
  }
  for (const char* vr : kShort) {
    if (vr[0] == a && vr[1] == b) {
      *long_form = false;
      return true;
    }
  }
  return false;
}

absl::Status Bad(uint64_t at, const std::string& what) {
  return absl::InvalidArgumentError(absl::StrCat(
      "not a well-formed DICOM data set: ", what, " at byte ", at));
}

// The walk. Frames are the open data set, items, sequences and fragment
// lists; `end` is where a frame with a defined length ends (kNoEnd: it ends
// with a delimiter, or the root with the data).
class Scanner {
 public:
  Scanner(ByteSource* src, Encoding root, const DatasetScanLimits& limits,
          uint64_t base, bool deflated = false)
      : src_(src), limits_(limits), base_(base), deflated_(deflated) {
    stack_.push_back({Frame::kRoot, kNoEnd, kNoEnd, root, 0});
  }

  absl::Status Run(DatasetScanResult* result) {
    while (true) {
      Frame& top = stack_.back();
      const uint64_t pos = src_->Position();
      if (top.end != kNoEnd) {
        if (pos == top.end) {
          if (top.kind == Frame::kRoot) break;
          stack_.pop_back();
          continue;
        }
        if (pos > top.end) return Bad(At(), "an element crosses its end");
      }
      if (top.end == kNoEnd && src_->AtEnd()) {
        if (top.kind == Frame::kRoot) break;
        return Bad(At(), "unterminated sequence or item");
      }
      if (absl::Status s = Step(); !s.ok()) return s;
    }
    if (stack_.size() != 1) return Bad(At(), "unterminated sequence or item");
    result->elements = elements_;
    result->deepest = deepest_;
    return absl::OkStatus();
  }

 private:
  struct Frame {
    enum Kind { kRoot, kItem, kSequence, kFragments } kind;
    uint64_t end;    // kNoEnd: undefined length
    uint64_t limit;  // the nearest defined end of this frame or an ancestor
    Encoding enc;
    int depth;  // sequences enclosing this frame's content
  };

  uint64_t At() const { return base_ + src_->Position(); }

  absl::Status ReadFailure() {
    if (const char* e = src_->error(); e != nullptr) {
      return absl::InternalError(e);
    }
    if (auto* inflate = dynamic_cast<InflateSource*>(src_)) {
      if (inflate->too_large()) {
        return Bad(At(), absl::StrCat("the deflated data set inflates past ",
                                      limits_.max_inflated_bytes, " bytes"));
      }
      if (inflate->bad_data()) return Bad(At(), "corrupt deflated data");
      if (inflate->truncated()) {
        return Bad(At(), "the deflated data ends before its end marker");
      }
    }
    return Bad(At(), "the data ends inside an element");
  }

  absl::Status CountElement() {
    if (++elements_ > limits_.max_elements) {
      return Bad(At(),
                 absl::StrCat("more than ", limits_.max_elements, " elements"));
    }
    return absl::OkStatus();
  }

  // A defined length: must fit within the enclosing frames and the data.
  absl::Status CheckFits(uint64_t length, const Frame& parent) {
    const uint64_t pos = src_->Position();
    if (parent.limit != kNoEnd && length > parent.limit - pos) {
      return Bad(At(), "a length runs past its enclosing item or sequence");
    }
    if (src_->Size() != kNoEnd && length > src_->Size() - pos) {
      return Bad(At(), "a length runs past the end of the data");
    }
    return absl::OkStatus();
  }

  absl::Status Push(Frame::Kind kind, uint64_t length, const Frame& parent,
                    Encoding enc, int depth) {
    uint64_t end = kNoEnd;
    uint64_t limit = parent.limit;
    if (length != kUndefined) {
      if (absl::Status s = CheckFits(length, parent); !s.ok()) return s;
      end = src_->Position() + length;
      limit = end;
    }
    if (depth > limits_.max_depth) {
      return Bad(At(), absl::StrCat("nesting deeper than ", limits_.max_depth,
                                    " sequences"));
    }
    deepest_ = std::max(deepest_, depth);
    stack_.push_back({kind, end, limit, enc, depth});
    return absl::OkStatus();
  }

  absl::Status Step() {
    const Frame top = stack_.back();
    const bool big = top.enc.big_endian;
    unsigned char head[8];
    if (!src_->Read(head, 4)) return ReadFailure();
    const uint16_t group = U16(head, big);
    const uint16_t element = U16(head + 2, big);

    if (top.kind == Frame::kSequence || top.kind == Frame::kFragments) {
      if (!src_->Read(head + 4, 4)) return ReadFailure();
      const uint32_t length = U32(head + 4, big);
      if (group == 0xFFFE && element == 0xE0DD) {  // sequence delimiter
        if (top.end != kNoEnd || length != 0) {
          return Bad(At(), "a misplaced sequence delimiter");
        }
        stack_.pop_back();
        return absl::OkStatus();
      }
      if (group != 0xFFFE || element != 0xE000) {
        return Bad(At(), "a sequence holds something other than items");
      }
      if (absl::Status s = CountElement(); !s.ok()) return s;
      if (top.kind == Frame::kFragments) {
        if (length == kUndefined) {
          return Bad(At(), "a pixel data fragment without a length");
        }
        if (absl::Status s = CheckFits(length, top); !s.ok()) return s;
        if (!src_->Skip(length)) return ReadFailure();
        return absl::OkStatus();
      }
      return Push(Frame::kItem, length, top, top.enc, top.depth);
    }

    // In the root or an item: a data element, or an item delimiter.
    if (group == 0xFFFE) {
      if (!src_->Read(head + 4, 4)) return ReadFailure();
      const uint32_t length = U32(head + 4, big);
      if (element == 0xE00D && top.kind == Frame::kItem && top.end == kNoEnd &&
          length == 0) {
        stack_.pop_back();
        return absl::OkStatus();
      }
      return Bad(At(), "a misplaced item or delimiter");
    }
    if (absl::Status s = CountElement(); !s.ok()) return s;
    bool sequence = false, un = false, other_binary = false;
    uint64_t length = 0;
    if (top.enc.explicit_vr) {
      if (!src_->Read(head + 4, 2)) return ReadFailure();
      const char a = static_cast<char>(head[4]), b = static_cast<char>(head[5]);
      bool long_form = false;
      if (!KnownVr(a, b, &long_form)) return Bad(At(), "an unknown VR");
      sequence = a == 'S' && b == 'Q';
      un = a == 'U' && b == 'N';
      other_binary = a == 'O' && (b == 'B' || b == 'W');
      if (long_form) {
        unsigned char l[6];
        if (!src_->Read(l, 6)) return ReadFailure();
        length = U32(l + 2, big);
      } else {
        unsigned char l[2];
        if (!src_->Read(l, 2)) return ReadFailure();
        length = U16(l, big);
      }
    } else {
      unsigned char l[4];
      if (!src_->Read(l, 4)) return ReadFailure();
      length = U32(l, false);
      // The VR of an implicit element is the dictionary's (DCMTK's own,
      // which is what its parser will use); an unknown tag is UN.
      const DcmEVR vr = DcmTag(group, element).getEVR();
      sequence = vr == EVR_SQ;
      un = vr == EVR_UN || vr == EVR_UNKNOWN || vr == EVR_UNKNOWN2B;
      other_binary = vr == EVR_OB || vr == EVR_OW || vr == EVR_ox;
    }
    if (sequence) {
      return Push(Frame::kSequence, length, top, top.enc, top.depth + 1);
    }
    if (un && !top.enc.explicit_vr && length != kUndefined && length >= 8) {
      // An implicit-VR element the public dictionary does not know (a
      // private one, say) may still be a sequence to DCMTK, which reads
      // private tags with its private dictionary: a value that starts with
      // an item is scanned as a sequence, so that nesting cannot hide in it.
      unsigned char first[4];
      if (!src_->Peek(first, 4)) return ReadFailure();
      if (U16(first, false) == 0xFFFE && U16(first + 2, false) == 0xE000) {
        return Push(Frame::kSequence, length, top, top.enc, top.depth + 1);
      }
    }
    if (length == kUndefined) {
      if (group == 0x7FE0 && element == 0x0010 && other_binary &&
          top.kind == Frame::kRoot) {
        // Encapsulated pixel data (PS3.5 A.4): fragments as items.
        return Push(Frame::kFragments, length, top, top.enc, top.depth + 1);
      }
      if (un) {
        // UN of undefined length is a sequence in implicit VR little
        // endian (PS3.5 6.2.2), and DCMTK parses it as one.
        return Push(Frame::kSequence, length, top, Encoding{false, false},
                    top.depth + 1);
      }
      return Bad(At(), "an undefined length on a value that cannot have one");
    }
    if (absl::Status s = CheckFits(length, top); !s.ok()) return s;
    if (deflated_ && !(group == 0x7FE0 && element == 0x0010) &&
        length > static_cast<uint64_t>(limits_.max_deflated_value_bytes)) {
      return Bad(At(), absl::StrCat("a value of ", length,
                                    " bytes in a deflated data set (at most ",
                                    limits_.max_deflated_value_bytes, ")"));
    }
    if (!src_->Skip(length)) return ReadFailure();
    return absl::OkStatus();
  }

  ByteSource* src_;
  const DatasetScanLimits limits_;
  const uint64_t base_;  // file offset of the data (for messages)
  const bool deflated_;
  std::vector<Frame> stack_;
  int64_t elements_ = 0;
  int deepest_ = 0;
};

// The transfer syntax as the scanner needs it, from DCMTK's table.
absl::StatusOr<std::pair<Encoding, bool>> EncodingOf(const std::string& uid) {
  DcmXfer xfer(uid.c_str());
  if (xfer.getXfer() == EXS_Unknown) {
    return absl::InvalidArgumentError(
        "not a well-formed DICOM file: unknown transfer syntax");
  }
  Encoding enc;
  enc.explicit_vr = xfer.isExplicitVR();
  enc.big_endian = xfer.getByteOrder() == EBO_BigEndian;
  const bool deflated = xfer.getStreamCompression() != ESC_none;
  return std::make_pair(enc, deflated);
}

absl::Status ScanWith(ByteSource* src, const std::string& uid,
                      const DatasetScanLimits& limits, uint64_t base,
                      DatasetScanResult* result) {
  absl::StatusOr<std::pair<Encoding, bool>> enc = EncodingOf(uid);
  if (!enc.ok()) return enc.status();
  result->transfer_syntax_uid = uid;
  if (enc->second) {
    InflateSource inflated(src, static_cast<uint64_t>(std::max<int64_t>(
                                    0, limits.max_inflated_bytes)));
    Scanner scanner(&inflated, enc->first, limits, 0, /*deflated=*/true);
    return scanner.Run(result);
  }
  Scanner scanner(src, enc->first, limits, base);
  return scanner.Run(result);
}

}  // namespace

absl::StatusOr<DatasetScanResult> ScanDatasetBytes(
    std::string_view bytes, const std::string& transfer_syntax_uid,
    const DatasetScanLimits& limits) {
  MemorySource src(bytes);
  DatasetScanResult result;
  if (absl::Status s = ScanWith(&src, transfer_syntax_uid, limits, 0, &result);
      !s.ok()) {
    return s;
  }
  return result;
}

namespace {

struct OpenFile {
  int fd = -1;
  uint64_t size = 0;
  ~OpenFile() {
    if (fd >= 0) ::close(fd);
  }
};

absl::Status Open(const std::string& path, OpenFile* file) {
  file->fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (file->fd < 0)
    return absl::NotFoundError("a received instance is missing");
  struct stat st;
  if (::fstat(file->fd, &st) != 0) {
    return absl::InternalError("a received instance cannot be read");
  }
  file->size = static_cast<uint64_t>(st.st_size);
  return absl::OkStatus();
}

absl::Status NotPart10(const char* what) {
  return absl::InvalidArgumentError(
      absl::StrCat("not a well-formed DICOM file: ", what));
}

absl::StatusOr<Part10Meta> ReadMeta(ByteSource& src) {
  unsigned char preamble[132];
  if (!src.Read(preamble, sizeof(preamble)) ||
      std::memcmp(preamble + 128, "DICM", 4) != 0) {
    return NotPart10("no DICM prefix");
  }
  // The file meta group (PS3.10 7.1), element by element up to the first
  // element of another group.
  Part10Meta meta;
  int elements = 0;
  while (true) {
    unsigned char head[8];
    if (!src.Peek(head, 2)) return NotPart10("the meta group is cut short");
    if (U16(head, false) != 0x0002) break;
    if (!src.Read(head, 8)) return NotPart10("the meta group is cut short");
    if (++elements > 64) return NotPart10("the meta group is too long");
    const uint16_t element = U16(head + 2, false);
    bool long_form = false;
    if (!KnownVr(static_cast<char>(head[4]), static_cast<char>(head[5]),
                 &long_form)) {
      return NotPart10("a meta element has an unknown VR");
    }
    uint64_t length = U16(head + 6, false);
    if (long_form) {
      unsigned char l[4];
      if (!src.Read(l, 4)) return NotPart10("the meta group is cut short");
      length = U32(l, false);
    }
    if (length > 64 * 1024) return NotPart10("a meta element is too long");
    std::string value(static_cast<size_t>(length), '\0');
    if (!src.Read(value.data(), value.size())) {
      return NotPart10("the meta group is cut short");
    }
    if (element == 0x0010) {
      // UI: trailing NUL or space padding.
      while (!value.empty() && (value.back() == '\0' || value.back() == ' ')) {
        value.pop_back();
      }
      meta.transfer_syntax_uid = value;
    }
  }
  if (meta.transfer_syntax_uid.empty()) {
    return NotPart10("no transfer syntax in the meta group");
  }
  meta.dataset_offset = static_cast<int64_t>(src.Position());
  return meta;
}

}  // namespace

absl::StatusOr<Part10Meta> ReadPart10Meta(const std::string& path) {
  OpenFile file;
  if (absl::Status s = Open(path, &file); !s.ok()) return s;
  FileSource src(file.fd, file.size, 0);
  return ReadMeta(src);
}

absl::StatusOr<DatasetScanResult> ScanPart10File(
    const std::string& path, const DatasetScanLimits& limits) {
  OpenFile file;
  if (absl::Status s = Open(path, &file); !s.ok()) return s;
  FileSource src(file.fd, file.size, 0);
  absl::StatusOr<Part10Meta> meta = ReadMeta(src);
  if (!meta.ok()) return meta.status();
  DatasetScanResult result;
  result.dataset_offset = meta->dataset_offset;
  if (absl::Status s =
          ScanWith(&src, meta->transfer_syntax_uid, limits, 0, &result);
      !s.ok()) {
    return s;
  }
  return result;
}

}  // namespace interslice::server::node
