#include "core/volume_io/volume_io.h"

#include <fcntl.h>
#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkImageFileWriter.h>
#include <itkImageIOBase.h>
#include <itkImportImageContainer.h>
#include <itkMetaDataObject.h>
#include <itkNiftiImageIO.h>
#include <itkNrrdImageIO.h>
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <exception>
#include <filesystem>
#include <limits>
#include <optional>
#include <random>
#include <span>
#include <system_error>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/common/status_macros.h"
#include "core/volume_io/parallel_gzip.h"

namespace interslice {
namespace {

enum class Format { kNifti, kNrrd };

struct FormatInfo {
  Format format;
  std::string extension;  // lower case, as matched
};

// Lower-case extension match on the file name (not the directories).
std::optional<FormatInfo> FormatOf(const std::string& path, bool for_reading) {
  const std::string name =
      absl::AsciiStrToLower(std::filesystem::path(path).filename().string());
  for (const char* ext : {".nii.gz", ".nii"}) {
    if (name.size() > std::strlen(ext) && absl::EndsWith(name, ext)) {
      return FormatInfo{Format::kNifti, ext};
    }
  }
  if (name.size() > 5 && absl::EndsWith(name, ".nrrd")) {
    return FormatInfo{Format::kNrrd, ".nrrd"};
  }
  if (for_reading && name.size() > 5 && absl::EndsWith(name, ".nhdr")) {
    return FormatInfo{Format::kNrrd, ".nhdr"};
  }
  return std::nullopt;
}

itk::ImageIOBase::Pointer MakeImageIO(Format format) {
  if (format == Format::kNifti) return itk::NiftiImageIO::New();
  return itk::NrrdImageIO::New();
}

std::string RandomSuffix() {
  thread_local std::mt19937_64 engine{std::random_device{}()};
  return absl::StrFormat("%016x", engine());
}

// "<dir>/.<stem>.tmp-<random><ext>": hidden, next to the target (same file
// system, so the rename is atomic), keeping the extension ITK goes by.
std::string TemporaryPath(const std::string& path, const FormatInfo& info) {
  const std::filesystem::path target(path);
  std::string name = target.filename().string();
  name.resize(name.size() - info.extension.size());
  return (target.parent_path() /
          absl::StrCat(".", name, ".tmp-", RandomSuffix(), info.extension))
      .string();
}

// Creates `path` as a new empty file (failing if it exists), so that a
// missing or unwritable directory is reported before ITK sees the path: ITK
// 5.2's NRRD writer throws on a failed nrrdSave without freeing its Nrrd,
// NrrdIoState and error string (about 3.5 KB per call), and NIfTI prints its
// own error to stderr.
absl::Status CreateEmptyFile(const std::string& path) {
  const int fd =
      open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
  if (fd < 0) {
    return absl::InternalError(
        std::error_code(errno, std::generic_category()).message());
  }
  close(fd);
  return absl::OkStatus();
}

// The pixel type's ITK image of `grid`'s geometry with `size` voxels, over
// `data` (not copied; writers only read it).
template <typename T>
typename itk::Image<T, 3>::Pointer WrapImage(
    const Grid& grid, const Index3& size, const T* data,
    const VolumeHeaderFields* fields = nullptr) {
  using ImageType = itk::Image<T, 3>;
  typename ImageType::Pointer image = ImageType::New();
  typename ImageType::SizeType itk_size;
  typename ImageType::SpacingType spacing;
  typename ImageType::PointType origin;
  typename ImageType::DirectionType direction;
  for (int a = 0; a < 3; ++a) {
    itk_size[a] = static_cast<itk::SizeValueType>(size[a]);
    spacing[a] = grid.spacing[a];
    origin[a] = grid.origin[a];
    for (int c = 0; c < 3; ++c) direction(a, c) = grid.direction[3 * a + c];
  }
  image->SetRegions(typename ImageType::RegionType(itk_size));
  image->SetSpacing(spacing);
  image->SetOrigin(origin);
  image->SetDirection(direction);
  auto container = ImageType::PixelContainer::New();
  container->SetImportPointer(const_cast<T*>(data), size[0] * size[1] * size[2],
                              /*LetContainerManageMemory=*/false);
  image->SetPixelContainer(container);
  if (fields != nullptr) {
    // ITK's NRRD writer writes the dictionary's string entries (other than
    // its own NRRD_ fields) as "key:=value" lines.
    for (const auto& [key, value] : fields->key_values) {
      itk::EncapsulateMetaData<std::string>(image->GetMetaDataDictionary(), key,
                                            value);
    }
  }
  return image;
}

// Writes `image` with ITK to `temp` (created empty beforehand);
// `compress` asks ITK's own compression (zlib level 1).
template <typename ImagePointer>
absl::Status ItkWrite(const ImagePointer& image, Format format,
                      const std::string& temp, bool compress) {
  using ImageType = typename ImagePointer::ObjectType;
  try {
    auto writer = itk::ImageFileWriter<ImageType>::New();
    auto io = MakeImageIO(format);
    io->SetCompressionLevel(1);
    writer->SetImageIO(io);
    writer->SetFileName(temp);
    writer->SetInput(image);
    writer->SetUseCompression(compress);
    writer->Update();
  } catch (const std::exception& e) {
    return absl::InternalError(e.what());
  }
  return absl::OkStatus();
}

absl::StatusOr<std::string> ReadWholeFile(const std::string& path) {
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f == nullptr) return absl::InternalError("cannot reopen the header");
  std::string bytes;
  char buffer[4096];
  size_t n;
  while ((n = std::fread(buffer, 1, sizeof(buffer), f)) > 0) {
    bytes.append(buffer, n);
  }
  const bool ok = !std::ferror(f);
  std::fclose(f);
  if (!ok) return absl::InternalError("cannot read the header back");
  return bytes;
}

// NIfTI-1 header offsets (nifti1.h): qform_code and sform_code (int16).
constexpr size_t kQformCodeOffset = 252, kSformCodeOffset = 254;

// Sets the NIfTI header's qform/sform codes that `fields` asks for.
void PatchNiftiCodes(char* header, const VolumeHeaderFields* fields) {
  if (fields == nullptr) return;
  if (fields->qform_code.has_value()) {
    const int16_t code = static_cast<int16_t>(*fields->qform_code);
    std::memcpy(header + kQformCodeOffset, &code, 2);
  }
  if (fields->sform_code.has_value()) {
    const int16_t code = static_cast<int16_t>(*fields->sform_code);
    std::memcpy(header + kSformCodeOffset, &code, 2);
  }
}

// The probe volume whose file ITK writes to learn the header: 2 voxels per
// axis (no axis of length 1, which some writers treat specially).
constexpr int64_t kProbeSize = 2;

// The header ITK writes for a volume of `grid` (geometry, pixel type): ITK
// writes a 2x2x2 probe volume of the same geometry uncompressed, and its
// header gets the real sizes (the only field that depends on them). The
// header and the voxels, gzipped in parallel, then make the same file as
// ITK's own (tests/core/volume_io compare the decompressed bytes).
// NIfTI-1: the 348-byte header and extension flag up to vox_offset, dim[1..3]
// patched. NRRD: the text header up to the blank line, "sizes:" patched and
// "encoding: raw" made "encoding: gzip".
template <typename T>
absl::StatusOr<std::string> ItkHeader(const Grid& grid, Format format,
                                      const std::string& probe_path,
                                      const VolumeHeaderFields* fields) {
  const std::vector<T> probe(kProbeSize * kProbeSize * kProbeSize, T{0});
  const Index3 probe_size = {kProbeSize, kProbeSize, kProbeSize};
  INTERSLICE_RETURN_IF_ERROR(CreateEmptyFile(probe_path));
  absl::Status written =
      ItkWrite(WrapImage<T>(grid, probe_size, probe.data(), fields), format,
               probe_path, /*compress=*/false);
  absl::StatusOr<std::string> bytes =
      written.ok() ? ReadWholeFile(probe_path) : written;
  std::error_code ec;
  std::filesystem::remove(probe_path, ec);
  if (!bytes.ok()) return bytes.status();
  const size_t data_bytes = probe.size() * sizeof(T);
  if (bytes->size() < data_bytes) {
    return absl::InternalError("ITK wrote a short probe file");
  }
  std::string header = bytes->substr(0, bytes->size() - data_bytes);

  if (format == Format::kNifti) {
    int32_t sizeof_hdr = 0;
    float vox_offset = 0;
    std::memcpy(&sizeof_hdr, header.data(), 4);
    if (header.size() >= 112) std::memcpy(&vox_offset, header.data() + 108, 4);
    int16_t dim[8] = {};
    if (header.size() >= 56) std::memcpy(dim, header.data() + 40, sizeof(dim));
    if (sizeof_hdr != 348 || vox_offset != static_cast<float>(header.size()) ||
        header.compare(344, 4, std::string("n+1\0", 4)) != 0 || dim[0] != 3 ||
        dim[1] != kProbeSize || dim[2] != kProbeSize || dim[3] != kProbeSize) {
      return absl::InternalError("unexpected NIfTI header from ITK");
    }
    for (int a = 0; a < 3; ++a) {
      if (grid.size[a] > std::numeric_limits<int16_t>::max()) {
        return absl::InvalidArgumentError(
            absl::StrCat("NIfTI-1 holds at most 32767 voxels per axis; axis ",
                         a, " has ", grid.size[a]));
      }
      dim[1 + a] = static_cast<int16_t>(grid.size[a]);
    }
    std::memcpy(header.data() + 40, dim, sizeof(dim));
    PatchNiftiCodes(header.data(), fields);
    return header;
  }

  // NRRD: lines up to and including the empty line that ends the header.
  const std::string probe_sizes = absl::StrFormat(
      "\nsizes: %d %d %d\n", kProbeSize, kProbeSize, kProbeSize);
  const std::string raw = "\nencoding: raw\n";
  const size_t sizes_at = header.find(probe_sizes);
  const size_t raw_at = header.find(raw);
  if (!absl::EndsWith(header, "\n\n") || sizes_at == std::string::npos ||
      raw_at == std::string::npos ||
      header.find(probe_sizes, sizes_at + 1) != std::string::npos) {
    return absl::InternalError("unexpected NRRD header from ITK");
  }
  header.replace(raw_at, raw.size(), "\nencoding: gzip\n");
  header.replace(header.find(probe_sizes), probe_sizes.size(),
                 absl::StrFormat("\nsizes: %d %d %d\n", grid.size[0],
                                 grid.size[1], grid.size[2]));
  return header;
}

// How each format's data are gzipped. NIfTI: independent libdeflate
// members (RFC 1952 allows any number; zlib's gzread in ITK, FSL, AFNI and
// dcm2niix, Python's gzip in nibabel, gzip(1) read them all), the best ratio
// and speed. NRRD: one member, because pynrrd decompresses a NRRD's data with
// a single zlib decompressobj, which stops after the first member; zlib's
// run-length strategy lets its blocks be deflated in parallel, at 4% more
// size on the phantom's distance field and much less on periodic data such
// as constant floats (bench/gzip_benchmark.cc).
volume_io_internal::GzipOptions GzipOptionsFor(Format format) {
  volume_io_internal::GzipOptions options;
  options.single_member = format == Format::kNrrd;
  return options;
}

// PatchNiftiCodes on an uncompressed .nii that ITK wrote.
absl::Status PatchNiftiFile(const std::string& path,
                            const VolumeHeaderFields* fields) {
  const int fd = open(path.c_str(), O_RDWR | O_CLOEXEC);
  if (fd < 0) {
    return absl::InternalError(
        std::error_code(errno, std::generic_category()).message());
  }
  char header[348];
  bool ok = ::pread(fd, header, sizeof(header), 0) ==
            static_cast<ssize_t>(sizeof(header));
  if (ok) {
    PatchNiftiCodes(header, fields);
    ok = ::pwrite(fd, header + kQformCodeOffset, 4, kQformCodeOffset) == 4;
  }
  if (close(fd) != 0) ok = false;
  return ok ? absl::OkStatus()
            : absl::InternalError("cannot set the NIfTI transform codes");
}

absl::Status WriteHeaderAndGzippedData(const std::string& path,
                                       const std::string& header,
                                       std::span<const std::byte> data,
                                       bool gzip_header,
                                       const ComputeContext& context) {
  const int fd = open(path.c_str(), O_WRONLY | O_TRUNC | O_CLOEXEC);
  if (fd < 0) {
    return absl::InternalError(
        std::error_code(errno, std::generic_category()).message());
  }
  const std::span<const std::byte> header_bytes(
      reinterpret_cast<const std::byte*>(header.data()), header.size());
  absl::Status status;
  if (gzip_header) {
    status = volume_io_internal::WriteParallelGzip(
        fd, {header_bytes, data}, GzipOptionsFor(Format::kNifti), context);
  } else {
    status =
        ::write(fd, header.data(), header.size()) ==
                static_cast<ssize_t>(header.size())
            ? absl::OkStatus()
            : absl::InternalError(
                  std::error_code(errno, std::generic_category()).message());
    if (status.ok()) {
      status = volume_io_internal::WriteParallelGzip(
          fd, {data}, GzipOptionsFor(Format::kNrrd), context);
    }
  }
  if (close(fd) != 0 && status.ok()) {
    status = absl::InternalError(
        std::error_code(errno, std::generic_category()).message());
  }
  return status;
}

template <typename T>
absl::Status WriteVolumeImpl(const Volume<T>& volume, const std::string& path,
                             const ComputeContext& context,
                             const VolumeHeaderFields* fields = nullptr) {
  const std::optional<FormatInfo> info = FormatOf(path, /*for_reading=*/false);
  if (!info.has_value()) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot write a volume to ", path,
                     ": unknown extension (expected .nii.gz, .nii or .nrrd)"));
  }
  if (absl::Status status = volume.grid.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot write ", path, ": ", status.message()));
  }
  if (static_cast<int64_t>(volume.data.size()) != volume.grid.VoxelCount()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "cannot write %s: the volume holds %d values but its grid has %d "
        "voxels",
        path, volume.data.size(), volume.grid.VoxelCount()));
  }
  if (fields != nullptr) {
    for (const std::optional<int>& code :
         {fields->qform_code, fields->sform_code}) {
      if (code.has_value() && (*code < 0 || *code > 5)) {
        return absl::InvalidArgumentError(absl::StrFormat(
            "cannot write %s: NIfTI transform code %d is not 0..5", path,
            *code));
      }
    }
    for (const auto& [key, value] : fields->key_values) {
      if (key.empty() || absl::StrContains(key, '\n') ||
          absl::StrContains(key, ":=") || absl::StrContains(value, '\n')) {
        return absl::InvalidArgumentError(absl::StrCat(
            "cannot write ", path, ": bad NRRD key/value field '", key, "'"));
      }
    }
  }
  const std::string temp = TemporaryPath(path, *info);
  if (absl::Status created = CreateEmptyFile(temp); !created.ok()) {
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", created.message()));
  }
  std::error_code ec;
  absl::Status status;
  if (info->extension == ".nii") {
    // Uncompressed: ITK writes the file itself.
    status = ItkWrite(
        WrapImage<T>(volume.grid, volume.grid.size, volume.data.data(), fields),
        info->format, temp, /*compress=*/false);
    if (status.ok() && fields != nullptr && info->format == Format::kNifti) {
      status = PatchNiftiFile(temp, fields);
    }
  } else {
    // Compressed: zlib in ITK (NIfTI's gzip, NRRD's gzip encoding) is one
    // thread at ~50-100 MB/s, and the float distance field barely compresses
    // (86%), so compression was most of a job's time. ITK provides the
    // header (see ItkHeader) and the voxels are deflated in parallel blocks
    // straight from memory, without an intermediate file. A .nii.gz is a
    // gzip stream of the whole .nii (header included); a NRRD's header is
    // text and only its data are gzipped.
    const FormatInfo probe_info{
        info->format, info->format == Format::kNifti ? ".nii" : ".nrrd"};
    absl::StatusOr<std::string> header = ItkHeader<T>(
        volume.grid, info->format,
        TemporaryPath(path.substr(0, path.size() - info->extension.size()) +
                          probe_info.extension,
                      probe_info),
        fields);
    status = header.status();
    if (status.ok()) {
      status = WriteHeaderAndGzippedData(
          temp, *header, std::as_bytes(std::span(volume.data)),
          /*gzip_header=*/info->format == Format::kNifti, context);
    }
  }
  if (!status.ok()) {
    std::filesystem::remove(temp, ec);
    if (status.code() == absl::StatusCode::kCancelled ||
        status.code() == absl::StatusCode::kDeadlineExceeded) {
      return status;
    }
    return absl::Status(status.code(), absl::StrCat("cannot write ", path, ": ",
                                                    status.message()));
  }
  std::filesystem::rename(temp, path, ec);
  if (ec) {
    const std::string reason = ec.message();
    std::filesystem::remove(temp, ec);
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", reason));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status WriteVolume(const Volume<float>& volume, const std::string& path,
                         const ComputeContext& context) {
  return WriteVolumeImpl(volume, path, context);
}

absl::Status WriteVolume(const Volume<uint8_t>& volume, const std::string& path,
                         const ComputeContext& context) {
  return WriteVolumeImpl(volume, path, context);
}

absl::Status WriteVolume(const Volume<uint16_t>& volume,
                         const std::string& path,
                         const ComputeContext& context) {
  return WriteVolumeImpl(volume, path, context);
}

absl::Status WriteVolume(const Volume<uint8_t>& volume, const std::string& path,
                         const VolumeHeaderFields& fields,
                         const ComputeContext& context) {
  return WriteVolumeImpl(volume, path, context, &fields);
}

absl::Status WriteVolume(const Volume<int16_t>& volume, const std::string& path,
                         const VolumeHeaderFields& fields,
                         const ComputeContext& context) {
  return WriteVolumeImpl(volume, path, context, &fields);
}

absl::Status WriteVolume(const Volume<uint16_t>& volume,
                         const std::string& path,
                         const VolumeHeaderFields& fields,
                         const ComputeContext& context) {
  return WriteVolumeImpl(volume, path, context, &fields);
}

absl::StatusOr<Volume<float>> ReadVolumeAsFloat(const std::string& path) {
  const std::optional<FormatInfo> info = FormatOf(path, /*for_reading=*/true);
  if (!info.has_value()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "cannot read a volume from ", path,
        ": unknown extension (expected .nii.gz, .nii, .nrrd or .nhdr)"));
  }
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("no such volume file: ", path));
  }

  using ImageType = itk::Image<float, 3>;
  ImageType::Pointer image;
  try {
    itk::ImageIOBase::Pointer io = MakeImageIO(info->format);
    io->SetFileName(path);
    io->ReadImageInformation();
    if (io->GetNumberOfComponents() != 1) {
      return absl::InvalidArgumentError(absl::StrCat(
          "cannot read ", path, ": it has ", io->GetNumberOfComponents(),
          " components per voxel; expected a scalar volume"));
    }
    for (unsigned d = 3; d < io->GetNumberOfDimensions(); ++d) {
      if (io->GetDimensions(d) > 1) {
        return absl::InvalidArgumentError(absl::StrCat(
            "cannot read ", path, ": it has ", io->GetNumberOfDimensions(),
            " dimensions; expected a 3D volume"));
      }
    }
    auto reader = itk::ImageFileReader<ImageType>::New();
    reader->SetImageIO(io);
    reader->SetFileName(path);
    reader->Update();
    image = reader->GetOutput();
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot read ", path, ": ", e.what()));
  }

  Volume<float> volume;
  const ImageType::RegionType region = image->GetBufferedRegion();
  for (int a = 0; a < 3; ++a) {
    volume.grid.size[a] = static_cast<int64_t>(region.GetSize(a));
    volume.grid.spacing[a] = image->GetSpacing()[a];
    volume.grid.origin[a] = image->GetOrigin()[a];
    for (int c = 0; c < 3; ++c) {
      volume.grid.direction[3 * a + c] = image->GetDirection()(a, c);
    }
  }
  if (absl::Status status = volume.grid.Validate(); !status.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "cannot read ", path, ": unsupported geometry: ", status.message()));
  }
  const float* data = image->GetBufferPointer();
  volume.data.assign(data, data + volume.grid.VoxelCount());
  return volume;
}

}  // namespace interslice

namespace interslice {
namespace {

// The NRRD text header: lines up to the first empty one (at most 1 MiB).
absl::StatusOr<std::vector<std::string>> NrrdHeaderLines(
    const std::string& path) {
  std::FILE* f = std::fopen(path.c_str(), "rb");
  if (f == nullptr) return absl::NotFoundError("cannot open it");
  std::vector<std::string> lines;
  std::string line;
  size_t total = 0;
  int c;
  while ((c = std::fgetc(f)) != EOF && total < (size_t{1} << 20)) {
    ++total;
    if (c != '\n') {
      line.push_back(static_cast<char>(c));
      continue;
    }
    if (!line.empty() && line.back() == '\r') line.pop_back();
    if (line.empty()) break;
    lines.push_back(std::move(line));
    line.clear();
  }
  std::fclose(f);
  return lines;
}

}  // namespace

absl::StatusOr<VolumeFileHeader> ReadVolumeFileHeader(const std::string& path) {
  const std::optional<FormatInfo> info = FormatOf(path, /*for_reading=*/true);
  if (!info.has_value()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "cannot read a volume from ", path,
        ": unknown extension (expected .nii.gz, .nii, .nrrd or .nhdr)"));
  }
  std::error_code ec;
  if (!std::filesystem::is_regular_file(path, ec)) {
    return absl::NotFoundError(absl::StrCat("no such volume file: ", path));
  }
  VolumeFileHeader header;
  header.nifti = info->format == Format::kNifti;
  try {
    itk::ImageIOBase::Pointer io = MakeImageIO(info->format);
    io->SetFileName(path);
    io->ReadImageInformation();
    if (io->GetNumberOfDimensions() < 3) {
      return absl::InvalidArgumentError(
          absl::StrCat("cannot read ", path, ": not a 3D volume"));
    }
    for (int a = 0; a < 3; ++a) {
      header.grid.size[a] = static_cast<int64_t>(io->GetDimensions(a));
      header.grid.spacing[a] = io->GetSpacing(a);
      header.grid.origin[a] = io->GetOrigin(a);
      const std::vector<double> axis = io->GetDirection(a);
      for (int c = 0; c < 3; ++c) {
        header.grid.direction[3 * c + a] =
            c < static_cast<int>(axis.size()) ? axis[c] : (a == c ? 1.0 : 0.0);
      }
    }
    const auto component = io->GetComponentType();
    header.component_type =
        itk::ImageIOBase::GetComponentTypeAsString(component);
    using IOComponent = itk::IOComponentEnum;
    header.integer_type = component != IOComponent::FLOAT &&
                          component != IOComponent::DOUBLE &&
                          component != IOComponent::UNKNOWNCOMPONENTTYPE;
  } catch (const std::exception& e) {
    return absl::InvalidArgumentError(
        absl::StrCat("cannot read ", path, ": ", e.what()));
  }
  if (header.nifti) {
    // The 348-byte NIfTI-1 header (gzread reads .nii and .nii.gz alike).
    gzFile f = gzopen(path.c_str(), "rb");
    char raw[348];
    const int n = f == nullptr ? -1 : gzread(f, raw, sizeof(raw));
    if (f != nullptr) gzclose(f);
    int32_t sizeof_hdr = 0;
    if (n == static_cast<int>(sizeof(raw))) std::memcpy(&sizeof_hdr, raw, 4);
    const bool swapped = sizeof_hdr == 0x5C010000;
    if (sizeof_hdr != 348 && !swapped) {
      return absl::InvalidArgumentError(
          absl::StrCat("cannot read ", path, ": not a NIfTI-1 header"));
    }
    auto int16_at = [&](size_t offset) {
      uint16_t v;
      std::memcpy(&v, raw + offset, 2);
      if (swapped) v = static_cast<uint16_t>((v << 8) | (v >> 8));
      return static_cast<int16_t>(v);
    };
    auto float_at = [&](size_t offset) {
      uint32_t v;
      std::memcpy(&v, raw + offset, 4);
      if (swapped) v = __builtin_bswap32(v);
      float f32;
      std::memcpy(&f32, &v, 4);
      return static_cast<double>(f32);
    };
    header.qform_code = int16_at(kQformCodeOffset);
    header.sform_code = int16_at(kSformCodeOffset);
    header.scl_slope = float_at(112);
    header.scl_inter = float_at(116);
  } else {
    absl::StatusOr<std::vector<std::string>> lines = NrrdHeaderLines(path);
    if (!lines.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("cannot read ", path, ": ", lines.status().message()));
    }
    for (const std::string& line : *lines) {
      if (line.empty() || line[0] == '#') continue;
      const size_t kv = line.find(":=");
      const size_t field = line.find(": ");
      if (kv != std::string::npos &&
          (field == std::string::npos || kv < field)) {
        header.key_values.emplace_back(line.substr(0, kv), line.substr(kv + 2));
      } else if (field != std::string::npos &&
                 line.substr(0, field) == "space") {
        header.nrrd_space = line.substr(field + 2);
      }
    }
  }
  return header;
}

}  // namespace interslice
