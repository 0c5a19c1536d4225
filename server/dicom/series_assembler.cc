#include "server/dicom/series_assembler.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <optional>
#include <tuple>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "core/common/sha256.h"
#include "dcmtk/config/osconfig.h"
#include "dcmtk/dcmdata/dcdeftag.h"
#include "dcmtk/dcmdata/dcfilefo.h"
#include "dcmtk/dcmdata/dcuid.h"
#include "nlohmann/json.hpp"
#include "server/dicom/dataset_scan.h"
#include "server/job_manager.h"
#include "server/log_safe.h"
#include "server/metrics.h"
#include "server/spool.h"
#include "spdlog/spdlog.h"

namespace interslice::server::dicom {
namespace {

namespace fs = std::filesystem;

// In a series folder: one file per association storing into it right now,
// and the record of why the series is incomplete.
constexpr char kOpenPrefix[] = "open-";
constexpr char kIncompleteFile[] = "incomplete.json";

void FsyncPath(const std::string& path, bool directory) {
  const int fd =
      ::open(path.c_str(), directory ? (O_RDONLY | O_DIRECTORY) : O_RDONLY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

// fsync that reports failure (the instance file: success must mean kept).
absl::Status FsyncFile(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return absl::InternalError("cannot open a received instance");
  const int rc = ::fsync(fd);
  ::close(fd);
  if (rc != 0) {
    return absl::ResourceExhaustedError("cannot sync a received instance");
  }
  return absl::OkStatus();
}

std::string Key(const std::string& called_ae, const std::string& study,
                const std::string& series) {
  Sha256 hash;
  hash.Update(called_ae);
  hash.Update(std::string_view("\0", 1));
  hash.Update(study);
  hash.Update(std::string_view("\0", 1));
  hash.Update(series);
  return HexString(hash.Finish()).substr(0, 32);
}

std::string InstanceName(const std::string& sop_instance_uid) {
  Sha256 hash;
  hash.Update(sop_instance_uid);
  return HexString(hash.Finish()).substr(0, 32) + ".dcm";
}

std::string GetString(DcmItem* item, const DcmTagKey& tag) {
  OFString value;
  if (item->findAndGetOFStringArray(tag, value).good()) {
    return std::string(value.c_str());
  }
  return "";
}

// What a segmentation references: its first SEG or RTSTRUCT instance (in
// name order), the referenced SeriesInstanceUID and the studies to look in.
struct SegmentationRef {
  std::string file;
  std::string series_uid;
  std::vector<std::string> study_uids;  // the instance's own first
};

std::optional<SegmentationRef> ReadSegmentationRef(const std::string& dir) {
  std::error_code ec;
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    if (entry.path().extension() == ".dcm") files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  for (const std::string& file : files) {
    DcmFileFormat ff;
    if (ff.loadFileUntilTag(file.c_str(), EXS_Unknown, EGL_noChange,
                            DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
            .bad()) {
      continue;
    }
    DcmDataset* ds = ff.getDataset();
    const std::string sop_class = GetString(ds, DCM_SOPClassUID);
    SegmentationRef ref;
    ref.file = file;
    const std::string own_study = GetString(ds, DCM_StudyInstanceUID);
    if (!own_study.empty()) ref.study_uids.push_back(own_study);
    if (sop_class == UID_SegmentationStorage) {
      DcmItem* series = nullptr;
      if (ds->findAndGetSequenceItem(DCM_ReferencedSeriesSequence, series, 0)
              .good()) {
        ref.series_uid = GetString(series, DCM_SeriesInstanceUID);
      }
    } else if (sop_class == UID_RTStructureSetStorage) {
      DcmItem *frame = nullptr, *study = nullptr, *series = nullptr;
      if (ds->findAndGetSequenceItem(DCM_ReferencedFrameOfReferenceSequence,
                                     frame, 0)
              .good() &&
          frame->findAndGetSequenceItem(DCM_RTReferencedStudySequence, study, 0)
              .good()) {
        const std::string referenced =
            GetString(study, DCM_ReferencedSOPInstanceUID);
        if (!referenced.empty() && referenced != own_study) {
          ref.study_uids.push_back(referenced);
        }
        if (study
                ->findAndGetSequenceItem(DCM_RTReferencedSeriesSequence, series,
                                         0)
                .good()) {
          ref.series_uid = GetString(series, DCM_SeriesInstanceUID);
        }
      }
    } else {
      continue;
    }
    if (ref.series_uid.empty() || ref.study_uids.empty()) return std::nullopt;
    return ref;
  }
  return std::nullopt;
}

// The *.dcm files of `dir`, in name order.
std::vector<std::string> DicomFiles(const std::string& dir) {
  std::error_code ec;
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    if (entry.path().extension() == ".dcm") files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  return files;
}

// The UIDs of a kept instance's header (empty where unreadable).
InstanceIds ReadInstanceIds(const std::string& file) {
  InstanceIds ids;
  DcmFileFormat ff;
  if (ff.loadFileUntilTag(file.c_str(), EXS_Unknown, EGL_noChange,
                          DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
          .bad()) {
    return ids;
  }
  DcmDataset* ds = ff.getDataset();
  ids.study_uid = GetString(ds, DCM_StudyInstanceUID);
  ids.series_uid = GetString(ds, DCM_SeriesInstanceUID);
  ids.sop_instance_uid = GetString(ds, DCM_SOPInstanceUID);
  ids.frame_of_reference_uid = GetString(ds, DCM_FrameOfReferenceUID);
  return ids;
}

// The FrameOfReferenceUID of a held series: its first instance's.
std::string HeldFrameOfReference(const std::string& held) {
  const std::vector<std::string> files = DicomFiles(held);
  return files.empty() ? ""
                       : ReadInstanceIds(files.front()).frame_of_reference_uid;
}

// SHA-256 of a kept instance's data set: the bytes after the meta group,
// as the sender sent them (the meta group is written by our listener and
// names the sender, which may differ for the same instance).
absl::StatusOr<std::string> DatasetSha256(const std::string& path) {
  absl::StatusOr<Part10Meta> meta = ReadPart10Meta(path);
  if (!meta.ok()) return meta.status();
  std::ifstream in(path, std::ios::binary);
  in.seekg(meta->dataset_offset);
  if (!in) return absl::InternalError("cannot read a kept instance");
  Sha256 hash;
  std::vector<char> buffer(1 << 16);
  while (in) {
    in.read(buffer.data(), static_cast<std::streamsize>(buffer.size()));
    hash.Update(std::string_view(buffer.data(), in.gcount()));
  }
  if (in.bad()) return absl::InternalError("cannot read a kept instance");
  return hash.Finish();
}

// A kept series' id: its folder's name under unmatched/, <key>-<unix ms>
// (checked before it becomes part of a path).
bool IsKeptId(const std::string& id) {
  const size_t dash = id.find('-');
  if (dash != 32 || id.size() < 34 || id.size() > 33 + 19) return false;
  for (size_t i = 0; i < id.size(); ++i) {
    const char c = id[i];
    const bool ok = i < 32    ? (c >= '0' && c <= '9') || (c >= 'a' && c <= 'f')
                    : i == 32 ? c == '-'
                              : c >= '0' && c <= '9';
    if (!ok) return false;
  }
  return true;
}

// origin.json of a series folder: the AE titles it was received with.
std::pair<std::string, std::string> ReadOrigin(const std::string& dir) {
  std::ifstream origin(fs::path(dir) / "origin.json");
  nlohmann::json j = nlohmann::json::parse(origin, nullptr, false);
  if (!j.is_object()) return {};
  return {j.value("calling_ae", ""), j.value("called_ae", "")};
}

std::string JobOrigin(const std::string& calling_ae,
                      const std::string& called_ae, const Rule& rule) {
  return absl::StrCat("dicom:", calling_ae, "->", called_ae, " rule ",
                      rule.name);
}

}  // namespace

SeriesFacts ReadSeriesFacts(const std::string& dir) {
  SeriesFacts facts;
  std::vector<double> positions;
  bool first = true;
  std::error_code ec;
  std::vector<std::string> files;
  for (const auto& entry : fs::directory_iterator(dir, ec)) {
    if (entry.path().extension() == ".dcm") files.push_back(entry.path());
  }
  std::sort(files.begin(), files.end());
  for (const std::string& file : files) {
    DcmFileFormat ff;
    if (ff.loadFileUntilTag(file.c_str(), EXS_Unknown, EGL_noChange,
                            DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
            .bad()) {
      continue;
    }
    DcmDataset* ds = ff.getDataset();
    if (first) {
      first = false;
      const std::string sop_class = GetString(ds, DCM_SOPClassUID);
      facts.segmentation = sop_class == UID_SegmentationStorage ||
                           sop_class == UID_RTStructureSetStorage;
      facts.modality = GetString(ds, DCM_Modality);
      facts.series_description = GetString(ds, DCM_SeriesDescription);
      facts.protocol_name = GetString(ds, DCM_ProtocolName);
      facts.body_part = GetString(ds, DCM_BodyPartExamined);
      Float64 thickness = 0;
      if (ds->findAndGetFloat64(DCM_SliceThickness, thickness).good() &&
          std::isfinite(thickness) && thickness > 0) {
        facts.slice_thickness_mm = thickness;
      }
    }
    Sint32 frames = 1;
    if (ds->findAndGetSint32(DCM_NumberOfFrames, frames).bad() || frames < 1) {
      frames = 1;
    }
    facts.slice_count += frames;
    // Classic single-frame images: their position along the slice normal.
    double ipp[3], iop[6];
    bool geometry = frames == 1;
    for (int i = 0; geometry && i < 3; ++i) {
      geometry =
          ds->findAndGetFloat64(DCM_ImagePositionPatient, ipp[i], i).good();
    }
    for (int i = 0; geometry && i < 6; ++i) {
      geometry =
          ds->findAndGetFloat64(DCM_ImageOrientationPatient, iop[i], i).good();
    }
    if (geometry) {
      const double n[3] = {iop[1] * iop[5] - iop[2] * iop[4],
                           iop[2] * iop[3] - iop[0] * iop[5],
                           iop[0] * iop[4] - iop[1] * iop[3]};
      positions.push_back(ipp[0] * n[0] + ipp[1] * n[1] + ipp[2] * n[2]);
    }
  }
  if (positions.size() >= 2) {
    std::sort(positions.begin(), positions.end());
    std::vector<double> gaps;
    for (size_t i = 1; i < positions.size(); ++i) {
      const double gap = positions[i] - positions[i - 1];
      if (gap > 1e-6) gaps.push_back(gap);
    }
    if (!gaps.empty()) {
      std::nth_element(gaps.begin(), gaps.begin() + gaps.size() / 2,
                       gaps.end());
      facts.slice_spacing_mm = gaps[gaps.size() / 2];
    }
  }
  return facts;
}

absl::StatusOr<ReceivedInstance> ReadReceivedInstance(
    const std::string& staged, int64_t received_bytes,
    const DatasetScanLimits& limits) {
  std::error_code ec;
  ReceivedInstance out;
  out.size = static_cast<int64_t>(fs::file_size(staged, ec));
  if (ec) return absl::InternalError("a received instance vanished");
  // The meta group is ours (DCMTK wrote it); what follows is as received.
  absl::StatusOr<Part10Meta> meta = ReadPart10Meta(staged);
  if (!meta.ok()) return meta.status();
  if (received_bytes >= 0 &&
      out.size - meta->dataset_offset != received_bytes) {
    // The writer's buffered tail was lost (a full disk shows at close).
    return absl::ResourceExhaustedError(
        "the disk is full: a received instance could not be written whole");
  }
  // Bounded first: DCMTK's parser below reads only what passed.
  if (absl::StatusOr<DatasetScanResult> scan = ScanPart10File(staged, limits);
      !scan.ok()) {
    return scan.status();
  }
  {
    DcmFileFormat ff;
    if (ff.loadFileUntilTag(staged.c_str(), EXS_Unknown, EGL_noChange,
                            DCM_MaxReadLength, ERM_autoDetect, DCM_PixelData)
            .bad()) {
      return absl::InvalidArgumentError("the instance is not readable DICOM");
    }
    DcmDataset* ds = ff.getDataset();
    out.ids.study_uid = GetString(ds, DCM_StudyInstanceUID);
    out.ids.series_uid = GetString(ds, DCM_SeriesInstanceUID);
    out.ids.sop_instance_uid = GetString(ds, DCM_SOPInstanceUID);
    out.ids.frame_of_reference_uid = GetString(ds, DCM_FrameOfReferenceUID);
  }
  if (out.ids.series_uid.empty() || out.ids.sop_instance_uid.empty()) {
    return absl::InvalidArgumentError(
        "the instance has no Series or SOP Instance UID");
  }
  return out;
}

absl::Status KeepReceivedFile(const std::string& staged,
                              const std::string& target) {
  if (absl::Status synced = FsyncFile(staged); !synced.ok()) return synced;
  if (::rename(staged.c_str(), target.c_str()) != 0) {
    return absl::ResourceExhaustedError(
        "the disk is full: cannot keep a received instance");
  }
  FsyncPath(fs::path(target).parent_path().string(), true);
  return absl::OkStatus();
}

SeriesAssembler::SeriesAssembler(const AssemblerOptions& options, RuleSet rules,
                                 Spool* spool, Metrics* metrics,
                                 JobSubmitter submitter)
    : options_(options),
      rules_(std::make_shared<const RuleSet>(std::move(rules))),
      spool_(spool),
      metrics_(metrics),
      submitter_(std::move(submitter)) {}

std::shared_ptr<const RuleSet> SeriesAssembler::rules() const {
  std::lock_guard<std::mutex> lock(rules_mu_);
  return rules_;
}

void SeriesAssembler::SetRules(RuleSet rules) {
  auto next = std::make_shared<const RuleSet>(std::move(rules));
  std::lock_guard<std::mutex> lock(rules_mu_);
  rules_ = std::move(next);
}

absl::StatusOr<std::unique_ptr<SeriesAssembler>> SeriesAssembler::Open(
    const AssemblerOptions& options, RuleSet rules, Spool* spool,
    Metrics* metrics, JobSubmitter submitter) {
  std::unique_ptr<SeriesAssembler> a(new SeriesAssembler(
      options, std::move(rules), spool, metrics, std::move(submitter)));
  if (absl::Status s = a->Recover(); !s.ok()) return s;
  return a;
}

SeriesAssembler::~SeriesAssembler() { Stop(); }

std::string SeriesAssembler::SeriesDir(const std::string& key) const {
  return (fs::path(options_.root) / "series" / key).string();
}

absl::Status SeriesAssembler::Recover() {
  std::error_code ec;
  for (const char* sub : {"incoming", "series", "completing", "unmatched"}) {
    fs::create_directories(fs::path(options_.root) / sub, ec);
    if (ec) {
      return absl::InternalError(
          absl::StrCat("cannot create the DICOM spool folder ", options_.root,
                       "/", sub, ": ", ec.message()));
    }
  }
  // Partial receptions: never acknowledged, so never kept.
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "incoming", ec)) {
    fs::remove_all(entry.path(), ec);
  }
  // Series being handed to a job when the server stopped: back to series/
  // (merged with instances that arrived since), to be completed again.
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "completing", ec)) {
    const std::string name = entry.path().filename().string();
    const std::string back = SeriesDir(name.substr(0, name.rfind('-')));
    if (!fs::exists(back, ec)) {
      fs::rename(entry.path(), back, ec);
      continue;
    }
    for (const auto& f : fs::directory_iterator(entry.path(), ec)) {
      if (f.path().extension() == ".dcm") {
        fs::rename(f.path(), fs::path(back) / f.path().filename(), ec);
      }
    }
    fs::remove_all(entry.path(), ec);
  }
  const auto now = std::chrono::steady_clock::now();
  int recovered = 0, interrupted = 0;
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "series", ec)) {
    if (!entry.is_directory()) continue;
    const std::string key = entry.path().filename().string();
    Pending p;
    std::ifstream origin(entry.path() / "origin.json");
    nlohmann::json j = nlohmann::json::parse(origin, nullptr, false);
    if (j.is_object()) {
      p.called_ae = j.value("called_ae", "");
      p.calling_ae = j.value("calling_ae", "");
    }
    bool was_open = false;
    for (const auto& f : fs::directory_iterator(entry.path(), ec)) {
      const std::string name = f.path().filename().string();
      if (absl::StartsWith(name, kOpenPrefix)) {
        was_open = true;
        fs::remove(f.path(), ec);
        continue;
      }
      if (f.path().extension() != ".dcm") continue;
      ++p.instances;
      p.bytes += static_cast<int64_t>(f.file_size(ec));
    }
    if (p.called_ae.empty() || (p.instances == 0 && !was_open)) {
      fs::remove_all(entry.path(), ec);
      continue;
    }
    // The waits start over: the server cannot know how long it was down,
    // and a sender may still be retrying.
    p.last_arrival = now;
    std::ifstream incomplete(entry.path() / kIncompleteFile);
    nlohmann::json k = nlohmann::json::parse(incomplete, nullptr, false);
    if (k.is_object()) p.incomplete = k.value("reason", "incomplete");
    if (const std::string held = NewestHeld(key); !held.empty()) {
      p.held_frame_of_reference = HeldFrameOfReference(held);
    }
    if (spool_ != nullptr) spool_->Add(p.bytes);
    Pending& kept = pending_[key] = p;
    if (was_open) {
      // An association was storing into it when the server stopped: what
      // it would have sent next never arrived.
      MarkIncomplete(key, kept,
                     "the server stopped while it was being received");
      ++interrupted;
    }
    FsyncPath(entry.path().string(), true);
    ++recovered;
  }
  int64_t unmatched_bytes =
      TreeSize((fs::path(options_.root) / "unmatched").string());
  if (spool_ != nullptr) spool_->Add(unmatched_bytes);
  if (recovered > 0) {
    spdlog::info(
        "dicom: {} series received before the restart wait for "
        "completion again ({} of them interrupted mid-association, now "
        "incomplete)",
        recovered, interrupted);
  }
  return absl::OkStatus();
}

void SeriesAssembler::Start() {
  std::lock_guard<std::mutex> lock(mu_);
  if (thread_.joinable()) return;
  stopping_ = false;
  thread_ = std::thread([this] { Loop(); });
}

void SeriesAssembler::Stop() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    stopping_ = true;
  }
  cv_.notify_all();
  if (thread_.joinable()) thread_.join();
}

int SeriesAssembler::pending_series() {
  std::lock_guard<std::mutex> lock(mu_);
  return static_cast<int>(pending_.size());
}

std::string SeriesAssembler::StagingPath() {
  std::lock_guard<std::mutex> lock(mu_);
  return (fs::path(options_.root) / "incoming" /
          absl::StrCat(::getpid(), "-", next_staging_++, ".part"))
      .string();
}

uint64_t SeriesAssembler::BeginAssociation(const std::string& calling_ae,
                                           const std::string& called_ae) {
  std::lock_guard<std::mutex> lock(mu_);
  const uint64_t id = ++next_association_;
  Association& a = associations_[id];
  a.calling_ae = calling_ae;
  a.called_ae = called_ae;
  return id;
}

void SeriesAssembler::MarkIncomplete(const std::string& key, Pending& p,
                                     const std::string& reason) {
  // Only an association that begins after this moment can complete it.
  p.incomplete_after = next_association_;
  p.release_requested = false;
  if (p.incomplete.has_value()) return;
  p.incomplete = reason;
  nlohmann::json j = {{"reason", reason}, {"since_unix_ms", UnixMillisNow()}};
  if (absl::Status s = WriteFileAtomically(
          (fs::path(SeriesDir(key)) / kIncompleteFile).string(),
          j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace));
      !s.ok()) {
    // Kept in memory all the same; after a restart the open-<n> files of
    // an interrupted association mark it again.
    spdlog::error("dicom: cannot record that a series is incomplete: {}",
                  LogSafe(s.message()));
  }
  if (metrics_ != nullptr) metrics_->DicomEvent("series_incomplete");
  spdlog::warn(
      "dicom: a series from {} -> {} ({} instance(s)) is incomplete: {}; it "
      "makes no job until a sender completes it, and is dropped if nothing "
      "of it arrives for {} s",
      LogSafe(p.calling_ae), LogSafe(p.called_ae), p.instances, reason,
      options_.unmatched_retention_seconds);
}

std::string SeriesAssembler::NewestHeld(const std::string& key) const {
  std::error_code ec;
  std::string held;
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string name = entry.path().filename().string();
    // <key>-<ms>: names sort by time within a key while the times have as
    // many digits, which holds for centuries.
    if (absl::StartsWith(name, key + "-") && entry.path().string() > held) {
      held = entry.path().string();
    }
  }
  return held;
}

// Hard-links (or copies) the instances of `from` that `dir` lacks into it.
// Returns the instances and bytes added.
static std::pair<int64_t, int64_t> CarryInstances(const std::string& from,
                                                  const std::string& dir) {
  std::error_code ec;
  int64_t n = 0, bytes = 0;
  for (const auto& f : fs::directory_iterator(from, ec)) {
    if (f.path().extension() != ".dcm") continue;
    const fs::path target = fs::path(dir) / f.path().filename();
    if (fs::exists(target, ec)) continue;  // a newer copy arrived
    std::error_code link;
    fs::create_hard_link(f.path(), target, link);
    if (link) fs::copy_file(f.path(), target, link);
    if (link) continue;
    ++n;
    bytes += static_cast<int64_t>(fs::file_size(target, ec));
  }
  return {n, bytes};
}

absl::Status SeriesAssembler::StartSeries(const std::string& key, Pending& p,
                                          const Association& a,
                                          const std::string& held) {
  std::error_code ec;
  const std::string dir = SeriesDir(key);
  fs::create_directories(dir, ec);
  if (ec) return absl::ResourceExhaustedError("cannot create a series folder");
  nlohmann::json origin = {{"called_ae", a.called_ae},
                           {"calling_ae", a.calling_ae}};
  if (absl::Status s = WriteFileAtomically(
          (fs::path(dir) / "origin.json").string(),
          origin.dump(-1, ' ', false,
                      nlohmann::json::error_handler_t::replace));
      !s.ok()) {
    fs::remove_all(dir, ec);
    return absl::ResourceExhaustedError(s.message());
  }
  p.called_ae = a.called_ae;
  p.calling_ae = a.calling_ae;
  // The series was complete before (its job made, or no rule matched) and
  // is held: the next job takes those instances too.
  if (!held.empty()) {
    const bool had_job = fs::exists(fs::path(held) / "job", ec);
    const auto [n, bytes] = CarryInstances(held, dir);
    p.instances += n;
    p.bytes += bytes;
    p.carried = n;
    // Hard links share the held copy's blocks; counted again all the same,
    // as a job's hard-linked upload is.
    if (spool_ != nullptr) spool_->Add(bytes);
    spdlog::info(
        "dicom: a series from {} -> {} that {} received more instances; "
        "it waits for completion again with its {} earlier instance(s)",
        LogSafe(a.calling_ae), LogSafe(a.called_ae),
        had_job ? "already made its job" : "was held without a job", n);
  }
  FsyncPath((fs::path(options_.root) / "series").string(), true);
  return absl::OkStatus();
}

absl::StatusOr<std::string> SeriesAssembler::AddInstance(
    uint64_t association, const std::string& staged, int64_t received_bytes) {
  std::error_code ec;
  struct Cleanup {
    const std::string& path;
    bool keep = false;
    ~Cleanup() {
      if (!keep) ::unlink(path.c_str());
    }
  } cleanup{staged};
  // Refused before its series is known: every series of the association
  // misses an instance.
  auto refuse_unknown = [&](absl::Status status) -> absl::Status {
    InstanceRefused(association);
    return status;
  };
  absl::StatusOr<ReceivedInstance> received =
      ReadReceivedInstance(staged, received_bytes, options_.scan_limits);
  if (!received.ok()) return refuse_unknown(received.status());
  const int64_t size = received->size;
  const InstanceIds& ids = received->ids;
  std::string called_ae;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto a = associations_.find(association);
    if (a == associations_.end()) {
      return absl::InternalError("an instance outside an association");
    }
    called_ae = a->second.called_ae;
  }
  const std::string key = Key(called_ae, ids.study_uid, ids.series_uid);
  const std::string dir = SeriesDir(key);
  const std::string target =
      (fs::path(dir) / InstanceName(ids.sop_instance_uid)).string();
  absl::Status synced = FsyncFile(staged);

  std::lock_guard<std::mutex> lock(mu_);
  Association& a = associations_[association];
  auto it = pending_.find(key);
  // A refusal of an instance whose series is known: the series misses it.
  auto refuse = [&](absl::Status status) -> absl::Status {
    a.refused.insert(key);
    auto p = pending_.find(key);
    if (p != pending_.end()) {
      MarkIncomplete(
          key, p->second,
          absl::StrCat("an instance was refused (", status.message(), ")"));
    }
    return status;
  };
  if (!synced.ok()) return refuse(synced);
  const bool fresh = it == pending_.end();
  // A late instance of a held series (see "Another frame of reference").
  const std::string held = fresh ? NewestHeld(key) : "";
  const std::string held_frame =
      fresh ? (held.empty() ? "" : HeldFrameOfReference(held))
            : it->second.held_frame_of_reference;
  if (!held_frame.empty() && !ids.frame_of_reference_uid.empty() &&
      ids.frame_of_reference_uid != held_frame) {
    if (metrics_ != nullptr) {
      metrics_->DicomEvent("instances_other_frame_of_reference");
    }
    spdlog::warn(
        "dicom: an instance from {} -> {} of a series held from before has "
        "another frame of reference than the held instances: refused, never "
        "merged into another geometry (send it as a series of its own)",
        LogSafe(a.calling_ae), LogSafe(a.called_ae));
    return refuse(absl::InvalidArgumentError(
        "the instance's frame of reference differs from that of the "
        "instances of its series held from before: refused, not merged into "
        "another geometry"));
  }
  Pending candidate;
  Pending& p = fresh ? candidate : it->second;
  const bool replaces = !fresh && fs::exists(target, ec);
  if (!replaces && p.instances + 1 > options_.max_instances_per_series) {
    return refuse(absl::ResourceExhaustedError(absl::StrCat(
        "the series already holds ", p.instances, " instances, the limit")));
  }
  if (p.bytes + size > options_.max_bytes_per_series) {
    return refuse(absl::ResourceExhaustedError(
        "the series would exceed the byte limit per series"));
  }
  if (spool_ != nullptr && !spool_->TryReserve(size)) {
    return refuse(absl::ResourceExhaustedError("the spool quota is reached"));
  }
  Pending* series = &p;
  if (fresh) {
    candidate.held_frame_of_reference = held_frame;
    if (absl::Status s = StartSeries(key, candidate, a, held); !s.ok()) {
      if (spool_ != nullptr) spool_->Release(size);
      return refuse(s);
    }
    series = &(pending_[key] = candidate);
  }
  // While the association stores into the series, a file says so: a
  // restart then knows the transfer was interrupted.
  const bool first_of_association = series->open.count(association) == 0;
  if (first_of_association) {
    const std::string marker =
        (fs::path(dir) / absl::StrCat(kOpenPrefix, association)).string();
    const int fd = ::open(marker.c_str(), O_CREAT | O_WRONLY | O_CLOEXEC, 0600);
    if (fd < 0) {
      if (spool_ != nullptr) spool_->Release(size);
      return refuse(absl::ResourceExhaustedError(
          "the disk is full: cannot record a transfer in progress"));
    }
    ::close(fd);
    series->open.insert(association);
    a.series.insert(key);
  }
  int64_t replaced_bytes = 0;
  const bool replaced = fs::exists(target, ec);
  if (replaced) {
    replaced_bytes = static_cast<int64_t>(fs::file_size(target, ec));
  }
  if (::rename(staged.c_str(), target.c_str()) != 0) {
    if (spool_ != nullptr) spool_->Release(size);
    return refuse(absl::ResourceExhaustedError(
        "the disk is full: cannot keep a received instance"));
  }
  cleanup.keep = true;
  FsyncPath(dir, true);
  if (replaced && spool_ != nullptr) spool_->Release(replaced_bytes);
  if (!replaced) ++series->instances;
  series->bytes += size - replaced_bytes;
  series->last_arrival = std::chrono::steady_clock::now();
  series->release_requested = false;
  return key;
}

void SeriesAssembler::InstanceRefused(uint64_t association) {
  std::lock_guard<std::mutex> lock(mu_);
  auto a = associations_.find(association);
  if (a == associations_.end()) return;
  a->second.tainted = true;
  for (const std::string& key : a->second.series) {
    auto p = pending_.find(key);
    if (p != pending_.end()) {
      MarkIncomplete(key, p->second,
                     "its association had an instance refused that could not "
                     "be read");
    }
  }
}

void SeriesAssembler::EndAssociation(uint64_t association, bool released) {
  bool any = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    auto it = associations_.find(association);
    if (it == associations_.end()) return;
    const Association a = std::move(it->second);
    associations_.erase(it);
    std::set<std::string> keys = a.series;
    keys.insert(a.refused.begin(), a.refused.end());
    for (const std::string& key : keys) {
      auto pit = pending_.find(key);
      if (pit == pending_.end()) continue;
      Pending& p = pit->second;
      const std::string dir = SeriesDir(key);
      if (p.open.erase(association) > 0) {
        std::error_code ec;
        fs::remove(fs::path(dir) / absl::StrCat(kOpenPrefix, association), ec);
      }
      const bool clean = released && !a.tainted && a.refused.count(key) == 0;
      if (!clean) {
        MarkIncomplete(key, p,
                       released ? "an instance of it was refused"
                                : "its association ended without a normal "
                                  "release (aborted, cut off or lost)");
      } else if (p.incomplete.has_value() && association > p.incomplete_after) {
        // A transfer that began after the series became incomplete stored
        // into it and ended well: the sender completed it.
        std::error_code ec;
        fs::remove(fs::path(dir) / kIncompleteFile, ec);
        spdlog::info(
            "dicom: a series from {} -> {} ({} instance(s)) is complete again "
            "after a later transfer of it",
            LogSafe(p.calling_ae), LogSafe(p.called_ae), p.instances);
        p.incomplete.reset();
      }
      if (clean && p.open.empty() && !p.incomplete.has_value()) {
        p.release_requested = true;
        any = true;
      }
      FsyncPath(dir, true);
    }
  }
  if (any) cv_.notify_all();
}

int SeriesAssembler::CompleteStableSeries() {
  const std::shared_ptr<const RuleSet> rules = this->rules();
  const auto now = std::chrono::steady_clock::now();
  const auto stable =
      std::chrono::duration_cast<std::chrono::steady_clock::duration>(
          std::chrono::duration<double>(rules->stable_seconds));
  std::vector<std::pair<std::string, Pending>> ready;
  std::vector<std::string> dirs;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (auto it = pending_.begin(); it != pending_.end();) {
      Pending& p = it->second;
      // Never while a transfer into it is open, never when incomplete.
      if (!p.open.empty() || p.incomplete.has_value()) {
        ++it;
        continue;
      }
      const bool stable_over = now - p.last_arrival >= stable;
      if (!stable_over && !p.release_requested) {
        ++it;
        continue;
      }
      if (!stable_over) {
        // Released normally before the stable wait ended: only a rule with
        // complete_on_release cuts the wait short. The files are all there
        // (and passed the bounded scan), so their headers are read now.
        SeriesFacts facts = ReadSeriesFacts(SeriesDir(it->first));
        facts.calling_ae = p.calling_ae;
        facts.called_ae = p.called_ae;
        const Rule* rule = rules->FirstMatch(facts);
        p.release_requested = false;
        if (rule == nullptr || !rule->complete_on_release) {
          ++it;
          continue;
        }
      }
      // Out of series/, so that a new instance of the series starts a new
      // folder instead of joining this one while its job is made.
      const std::string dir = (fs::path(options_.root) / "completing" /
                               absl::StrCat(it->first, "-", ++next_completion_))
                                  .string();
      if (::rename(SeriesDir(it->first).c_str(), dir.c_str()) != 0) {
        spdlog::error(
            "dicom: cannot move a complete series out of the way; "
            "it stays pending");
        ++it;
        continue;
      }
      ready.emplace_back(it->first, it->second);
      dirs.push_back(dir);
      it = pending_.erase(it);
    }
  }
  for (size_t i = 0; i < ready.size(); ++i) {
    Complete(ready[i].first, ready[i].second, dirs[i]);
  }
  return static_cast<int>(ready.size());
}

void SeriesAssembler::Complete(const std::string& key, const Pending& p,
                               const std::string& dir) {
  if (metrics_ != nullptr) metrics_->DicomEvent("series_completed");
  if (DropIfResentUnchanged(key, p, dir)) return;
  SeriesFacts facts = ReadSeriesFacts(dir);
  facts.calling_ae = p.calling_ae;
  facts.called_ae = p.called_ae;
  // One generation of the rules for this series (held while its job is
  // made: `rule` points into it).
  const std::shared_ptr<const RuleSet> rules = this->rules();
  const Rule* rule = rules->FirstMatch(facts);
  const std::string from =
      absl::StrCat(LogSafe(p.calling_ae), " -> ", LogSafe(p.called_ae));
  if (rule == nullptr) {
    KeepUnmatched(key, dir);
    spdlog::warn(
        "dicom: no rule of rule set {} matched a series from {} ({} "
        "instance(s), modality {}): {}; kept for {} s, then removed",
        LogSafe(rules->path), from, p.instances, LogSafe(facts.modality),
        LogSafe(rules->ExplainNoMatch(facts)),
        options_.unmatched_retention_seconds);
    return;
  }
  const std::string origin = JobOrigin(p.calling_ae, p.called_ae, *rule);
  if (rule->job.has_fill()) {
    CompleteFill(key, p, dir, *rule, origin);
    return;
  }
  // The job's admission reserves these bytes again (its upload is these
  // files, hard-linked): hand our reservation over first, so that a series
  // near the quota can still become its own job.
  if (spool_ != nullptr) spool_->Release(p.bytes);
  absl::StatusOr<std::string> job = submitter_(rule->job, dir, origin, "");
  if (!job.ok()) {
    if (spool_ != nullptr) spool_->Add(p.bytes);
    // Back into series/ so that it is tried again after another stable
    // wait (a full queue, a drain) and survives a restart.
    PutBack(key, p, dir);
    spdlog::warn(
        "dicom: rule {} matched a series from {} but its job could "
        "not be made ({}); trying again after another stable wait",
        LogSafe(rule->name), from, LogSafe(job.status().message()));
    return;
  }
  // Held for the retention time: a segmentation drawn on it may follow,
  // and so may more instances of it (the next job then takes all of them).
  // Counted in the quota again although the job's copy shares its blocks.
  if (spool_ != nullptr) spool_->Add(p.bytes);
  KeepUnmatched(key, dir, *job);
  if (metrics_ != nullptr) metrics_->DicomEvent("jobs_created");
  spdlog::info(
      "dicom: job={} made by rule {} for a series from {} ({} "
      "instance(s){})",
      *job, LogSafe(rule->name), from, p.instances,
      p.carried > 0 ? absl::StrCat(", ", p.carried, " of them held from before")
                    : "");
}

void SeriesAssembler::PutBack(const std::string& key, const Pending& p,
                              const std::string& dir) {
  std::error_code ec;
  std::lock_guard<std::mutex> lock(mu_);
  const std::string back = SeriesDir(key);
  if (!fs::exists(back, ec) && ::rename(dir.c_str(), back.c_str()) == 0) {
    Pending again = p;
    again.last_arrival = std::chrono::steady_clock::now();
    again.release_requested = false;
    pending_[key] = again;
  } else {
    // New instances arrived meanwhile: merge ours into their folder (theirs
    // are newer where both have an instance).
    for (const auto& f : fs::directory_iterator(dir, ec)) {
      if (f.path().extension() != ".dcm") continue;
      const fs::path target = fs::path(back) / f.path().filename();
      if (fs::exists(target, ec)) continue;
      fs::rename(f.path(), target, ec);
    }
    fs::remove_all(dir, ec);
    auto it = pending_.find(key);
    if (it != pending_.end()) {
      int64_t n = 0, bytes = 0;
      for (const auto& f : fs::directory_iterator(back, ec)) {
        if (f.path().extension() != ".dcm") continue;
        ++n;
        bytes += static_cast<int64_t>(f.file_size(ec));
      }
      // Counted so far: theirs and ours; now: what the folder holds.
      if (spool_ != nullptr) spool_->Add(bytes - it->second.bytes - p.bytes);
      it->second.instances = n;
      it->second.bytes = bytes;
      if (!it->second.waiting_since) it->second.waiting_since = p.waiting_since;
    }
  }
}

void SeriesAssembler::KeepUnmatched(const std::string& key,
                                    const std::string& dir,
                                    const std::string& job_id) {
  std::error_code ec;
  if (!job_id.empty()) {
    std::ofstream(fs::path(dir) / "job") << job_id << "\n";
  }
  const std::string previous = NewestHeld(key);
  const std::string kept = (fs::path(options_.root) / "unmatched" /
                            absl::StrCat(key, "-", UnixMillisNow()))
                               .string();
  fs::rename(dir, kept, ec);
  if (ec) return;
  // The older copy is a subset of this one (its instances were carried
  // over when the series grew): no longer needed.
  if (!previous.empty() && previous != kept) {
    const int64_t bytes = TreeSize(previous);
    fs::remove_all(previous, ec);
    if (spool_ != nullptr) spool_->Release(bytes);
  }
  // Instances that arrived while this copy was being completed form a new
  // series already: it takes the completed ones too.
  std::lock_guard<std::mutex> lock(mu_);
  auto it = pending_.find(key);
  if (it != pending_.end()) {
    const auto [n, bytes] = CarryInstances(kept, SeriesDir(key));
    it->second.instances += n;
    it->second.bytes += bytes;
    it->second.carried += n;
    if (spool_ != nullptr) spool_->Add(bytes);
  }
}

void SeriesAssembler::DropStaleIncomplete() {
  const auto now = std::chrono::steady_clock::now();
  const auto wait =
      std::chrono::duration<double>(options_.unmatched_retention_seconds);
  std::vector<std::pair<std::string, Pending>> dropped;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (auto it = pending_.begin(); it != pending_.end();) {
      const Pending& p = it->second;
      if (!p.incomplete.has_value() || !p.open.empty() ||
          now - p.last_arrival < wait) {
        ++it;
        continue;
      }
      std::error_code ec;
      fs::remove_all(SeriesDir(it->first), ec);
      if (spool_ != nullptr) spool_->Release(p.bytes);
      dropped.emplace_back(it->first, p);
      it = pending_.erase(it);
    }
  }
  for (const auto& [key, p] : dropped) {
    if (metrics_ != nullptr) metrics_->DicomEvent("series_incomplete_dropped");
    spdlog::warn(
        "dicom: an incomplete series from {} -> {} ({} instance(s); {}) "
        "received nothing for {} s and was dropped; no job was made of it",
        LogSafe(p.calling_ae), LogSafe(p.called_ae), p.instances,
        p.incomplete.value_or(""), options_.unmatched_retention_seconds);
  }
}

std::string SeriesAssembler::CompleteFill(const std::string& key,
                                          const Pending& p,
                                          const std::string& dir,
                                          const Rule& rule,
                                          const std::string& origin) {
  std::error_code ec;
  const std::string from =
      absl::StrCat(LogSafe(p.calling_ae), " -> ", LogSafe(p.called_ae));
  std::optional<SegmentationRef> ref = ReadSegmentationRef(dir);
  if (!ref.has_value()) {
    KeepUnmatched(key, dir);
    spdlog::warn(
        "dicom: rule {} matched a segmentation from {} that names no "
        "referenced series; kept for {} s, then removed",
        LogSafe(rule.name), from, options_.unmatched_retention_seconds);
    return "";
  }
  // The referenced series, by the keys it would have been filed under.
  std::string held;
  bool pending = false;
  {
    std::lock_guard<std::mutex> lock(mu_);
    for (const std::string& study : ref->study_uids) {
      const std::string series_key = Key(p.called_ae, study, ref->series_uid);
      if (pending_.count(series_key) > 0) pending = true;
      for (const auto& entry :
           fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
        const std::string name = entry.path().filename().string();
        // <key>-<ms>: the newest copy (names sort by time within a key
        // only when the times have as many digits, which holds for years).
        if (absl::StartsWith(name, series_key + "-") &&
            entry.path().string() > held) {
          held = entry.path().string();
        }
      }
    }
  }
  if (held.empty()) {
    Pending again = p;
    const auto now = std::chrono::steady_clock::now();
    if (!again.waiting_since) {
      again.waiting_since = now;
      spdlog::info(
          "dicom: a segmentation from {} (rule {}) waits for the series it "
          "references{}",
          from, LogSafe(rule.name),
          pending ? " (still being received)" : " (not received yet)");
    }
    const auto waited = now - *again.waiting_since;
    if (waited <
        std::chrono::duration<double>(options_.unmatched_retention_seconds)) {
      PutBack(key, again, dir);
      return "";
    }
    KeepUnmatched(key, dir);
    spdlog::warn(
        "dicom: a segmentation from {} (rule {}) waited {} s for the series "
        "it references in vain; kept for {} s, then removed",
        from, LogSafe(rule.name), options_.unmatched_retention_seconds,
        options_.unmatched_retention_seconds);
    return "";
  }
  if (spool_ != nullptr) spool_->Release(p.bytes);
  absl::StatusOr<std::string> job =
      submitter_(rule.job, held, origin, ref->file);
  if (!job.ok()) {
    if (spool_ != nullptr) spool_->Add(p.bytes);
    PutBack(key, p, dir);
    spdlog::warn(
        "dicom: rule {} matched a segmentation from {} but its fill job "
        "could not be made ({}); trying again after another stable wait",
        LogSafe(rule.name), from, LogSafe(job.status().message()));
    return "";
  }
  fs::remove_all(dir, ec);
  if (metrics_ != nullptr) metrics_->DicomEvent("jobs_created");
  spdlog::info(
      "dicom: job={} (fill) made by rule {} for a segmentation from {} on a "
      "series held in the spool",
      *job, LogSafe(rule.name), from);
  return *job;
}

bool SeriesAssembler::DropIfResentUnchanged(const std::string& key,
                                            const Pending& p,
                                            const std::string& dir) {
  const std::string held = NewestHeld(key);
  if (held.empty()) return false;
  std::string job_id;
  if (!(std::ifstream(fs::path(held) / "job") >> job_id)) {
    return false;  // held without a job: the rules may have been fixed
  }
  if (options_.job_ended_without_results &&
      options_.job_ended_without_results(job_id)) {
    spdlog::info(
        "dicom: a series from {} -> {} whose job={} ended without results "
        "arrived again: its job is made again",
        LogSafe(p.calling_ae), LogSafe(p.called_ae), job_id);
    return false;
  }
  const std::vector<std::string> ours = DicomFiles(dir);
  const std::vector<std::string> theirs = DicomFiles(held);
  if (ours.size() != theirs.size()) return false;
  int64_t resent = 0;
  for (size_t i = 0; i < ours.size(); ++i) {
    // Names are hashes of the SOP Instance UID: the same set of instances.
    if (fs::path(ours[i]).filename() != fs::path(theirs[i]).filename()) {
      return false;
    }
    struct stat mine {
    }, held_one{};
    if (::stat(ours[i].c_str(), &mine) != 0 ||
        ::stat(theirs[i].c_str(), &held_one) != 0) {
      return false;
    }
    // Carried over from the held copy (a hard link): the same file.
    if (mine.st_dev == held_one.st_dev && mine.st_ino == held_one.st_ino) {
      continue;
    }
    absl::StatusOr<std::string> a = DatasetSha256(ours[i]);
    absl::StatusOr<std::string> b = DatasetSha256(theirs[i]);
    if (!a.ok() || !b.ok() || *a != *b) return false;
    ++resent;
  }
  std::error_code ec;
  fs::remove_all(dir, ec);
  if (spool_ != nullptr) spool_->Release(p.bytes);
  if (metrics_ != nullptr) metrics_->DicomEvent("series_resent_unchanged");
  spdlog::info(
      "dicom: {} instance(s) from {} -> {} of a series whose job={} was made "
      "arrived again, re-sent, unchanged: no job made, the held series "
      "stays",
      resent, LogSafe(p.calling_ae), LogSafe(p.called_ae), job_id);
  return true;
}

std::vector<KeptSeries> SeriesAssembler::ListKept() {
  const std::shared_ptr<const RuleSet> rules = this->rules();
  std::vector<KeptSeries> kept;
  std::error_code ec;
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string id = entry.path().filename().string();
    if (!IsKeptId(id)) continue;
    const std::string dir = entry.path().string();
    KeptSeries k;
    k.id = id;
    if (!absl::SimpleAtoi(id.substr(33), &k.kept_since_unix_ms)) continue;
    std::tie(k.calling_ae, k.called_ae) = ReadOrigin(dir);
    std::ifstream(fs::path(dir) / "job") >> k.job_id;
    const std::vector<std::string> files = DicomFiles(dir);
    if (files.empty()) continue;  // removed meanwhile
    k.instances = static_cast<int64_t>(files.size());
    const InstanceIds ids = ReadInstanceIds(files.front());
    k.study_uid = ids.study_uid;
    k.series_uid = ids.series_uid;
    SeriesFacts facts = ReadSeriesFacts(dir);
    facts.calling_ae = k.calling_ae;
    facts.called_ae = k.called_ae;
    k.modality = facts.modality;
    k.why = k.job_id.empty() ? absl::StrCat("no rule matched; the rules now: ",
                                            rules->ExplainNoMatch(facts))
                             : absl::StrCat("job ", k.job_id, " made");
    kept.push_back(std::move(k));
  }
  std::sort(kept.begin(), kept.end(),
            [](const KeptSeries& a, const KeptSeries& b) {
              return std::tie(a.kept_since_unix_ms, a.id) <
                     std::tie(b.kept_since_unix_ms, b.id);
            });
  return kept;
}

absl::StatusOr<KeptRerun> SeriesAssembler::RerunKept(const std::string& id) {
  const absl::Status not_found = absl::NotFoundError(
      "no kept series has that id (see `interslice kept list`; a kept series "
      "is removed at the end of its retention time)");
  if (!IsKeptId(id)) return not_found;
  const std::string key = id.substr(0, 32);
  const std::string held =
      (fs::path(options_.root) / "unmatched" / id).string();
  std::error_code ec;
  if (!fs::is_directory(held, ec)) return not_found;
  Pending p;
  std::tie(p.calling_ae, p.called_ae) = ReadOrigin(held);
  for (const std::string& file : DicomFiles(held)) {
    ++p.instances;
    p.bytes += static_cast<int64_t>(fs::file_size(file, ec));
  }
  if (p.instances == 0) return not_found;
  SeriesFacts facts = ReadSeriesFacts(held);
  facts.calling_ae = p.calling_ae;
  facts.called_ae = p.called_ae;
  // One generation of the rules, as in Complete.
  const std::shared_ptr<const RuleSet> rules = this->rules();
  const Rule* rule = rules->FirstMatch(facts);
  const std::string from =
      absl::StrCat(LogSafe(p.calling_ae), " -> ", LogSafe(p.called_ae));
  KeptRerun out;
  out.id = id;
  if (rule == nullptr) {
    out.not_matched =
        absl::StrCat("no rule matched: ", rules->ExplainNoMatch(facts));
    spdlog::info(
        "dicom: a kept series from {} ({} instance(s), modality {}) run "
        "again: still no rule of rule set {} matched: {}",
        from, p.instances, LogSafe(facts.modality), LogSafe(rules->path),
        LogSafe(rules->ExplainNoMatch(facts)));
    return out;
  }
  // Out of unmatched/ as CompleteStableSeries takes a series out of
  // series/: a late instance then starts a new folder, which KeepUnmatched
  // gives these instances once the job is made.
  std::string dir;
  {
    std::lock_guard<std::mutex> lock(mu_);
    dir = (fs::path(options_.root) / "completing" /
           absl::StrCat(key, "-", ++next_completion_))
              .string();
    if (pending_.count(key) > 0) {
      return absl::FailedPreconditionError(
          "more instances of this series are being received: it makes its "
          "job by the rules when they are complete");
    }
    if (::rename(held.c_str(), dir.c_str()) != 0) return not_found;
  }
  const std::string origin = JobOrigin(p.calling_ae, p.called_ae, *rule);
  spdlog::info(
      "dicom: a kept series from {} ({} instance(s)) run again on request: "
      "rule {} of rule set {} matches",
      from, p.instances, LogSafe(rule->name), LogSafe(rules->path));
  if (rule->job.has_fill()) {
    out.job_id = CompleteFill(key, p, dir, *rule, origin);
    if (out.job_id.empty()) {
      out.not_matched = absl::StrCat(
          "rule '", rule->name,
          "' matches this segmentation, but no job was made: the series it "
          "references is not held (see the server's log)");
    }
    return out;
  }
  // As Complete: the job's admission reserves the bytes again.
  if (spool_ != nullptr) spool_->Release(p.bytes);
  absl::StatusOr<std::string> job = submitter_(rule->job, dir, origin, "");
  if (!job.ok()) {
    if (spool_ != nullptr) spool_->Add(p.bytes);
    bool back = false;
    {
      std::lock_guard<std::mutex> lock(mu_);
      // Held again under its own name (its retention unchanged), unless a
      // late instance started the series again meanwhile: then it joins.
      back =
          pending_.count(key) == 0 && ::rename(dir.c_str(), held.c_str()) == 0;
    }
    if (!back) PutBack(key, p, dir);
    spdlog::warn(
        "dicom: rule {} matched a kept series from {} run again, but its job "
        "could not be made ({}); {}",
        LogSafe(rule->name), from, LogSafe(job.status().message()),
        back ? "it stays kept" : "it waits with the instances received since");
    return job.status();
  }
  if (spool_ != nullptr) spool_->Add(p.bytes);
  KeepUnmatched(key, dir, *job);
  if (metrics_ != nullptr) metrics_->DicomEvent("jobs_created");
  spdlog::info(
      "dicom: job={} made by rule {} for a kept series from {} ({} "
      "instance(s)), run again on request",
      *job, LogSafe(rule->name), from, p.instances);
  out.job_id = *job;
  return out;
}

absl::StatusOr<std::vector<KeptRerun>> SeriesAssembler::RerunAllUnmatched() {
  // Ids only (oldest first): RerunKept reads each series itself.
  std::vector<std::pair<int64_t, std::string>> ids;
  std::error_code ec;
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string id = entry.path().filename().string();
    int64_t since = 0;
    if (!IsKeptId(id) || !absl::SimpleAtoi(id.substr(33), &since) ||
        fs::exists(entry.path() / "job", ec)) {
      continue;
    }
    ids.emplace_back(since, id);
  }
  std::sort(ids.begin(), ids.end());
  std::vector<KeptRerun> out;
  std::vector<std::string> made;
  for (const auto& [since, id] : ids) {
    absl::StatusOr<KeptRerun> r = RerunKept(id);
    if (absl::IsNotFound(r.status())) continue;  // its retention ended
    if (!r.ok()) {
      return absl::Status(
          r.status().code(),
          absl::StrCat("kept series ", id, ": ", r.status().message(), " (",
                       made.size(), " job(s) made before it",
                       made.empty() ? "" : ": ", absl::StrJoin(made, ", "),
                       ")"));
    }
    if (!r->job_id.empty()) made.push_back(r->job_id);
    out.push_back(*std::move(r));
  }
  return out;
}

void SeriesAssembler::SweepUnmatched() {
  std::error_code ec;
  const int64_t now_ms = UnixMillisNow();
  for (const auto& entry :
       fs::directory_iterator(fs::path(options_.root) / "unmatched", ec)) {
    const std::string name = entry.path().filename().string();
    const size_t dash = name.rfind('-');
    int64_t made_ms = 0;
    if (dash == std::string::npos ||
        !absl::SimpleAtoi(name.substr(dash + 1), &made_ms)) {
      continue;
    }
    if (now_ms - made_ms <
        static_cast<int64_t>(options_.unmatched_retention_seconds * 1000)) {
      continue;
    }
    const int64_t bytes = TreeSize(entry.path().string());
    fs::remove_all(entry.path(), ec);
    if (spool_ != nullptr) spool_->Release(bytes);
    spdlog::info(
        "dicom: an unmatched series reached its retention time and "
        "was removed");
  }
}

void SeriesAssembler::Loop() {
  std::unique_lock<std::mutex> lock(mu_);
  while (!stopping_) {
    cv_.wait_for(lock, options_.poll_interval);
    if (stopping_) break;
    lock.unlock();
    CompleteStableSeries();
    const auto now = std::chrono::steady_clock::now();
    if (now - last_sweep_ > std::chrono::seconds(1)) {
      last_sweep_ = now;
      SweepUnmatched();
      DropStaleIncomplete();
    }
    lock.lock();
  }
}

}  // namespace interslice::server::dicom
