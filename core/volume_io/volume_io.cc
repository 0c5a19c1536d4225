#include "core/volume_io/volume_io.h"

#include <fcntl.h>
#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkImageFileWriter.h>
#include <itkImageIOBase.h>
#include <itkImportImageContainer.h>
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
#include <optional>
#include <random>
#include <system_error>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

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

// Compresses `from` into the gzip file `to` with zlib at level 1.
absl::Status GzipFile(const std::string& from, const std::string& to) {
  std::FILE* in = std::fopen(from.c_str(), "rb");
  if (in == nullptr) return absl::InternalError("cannot reopen the .nii");
  gzFile out = gzopen(to.c_str(), "wb1");
  if (out == nullptr) {
    std::fclose(in);
    return absl::InternalError("cannot create the .nii.gz");
  }
  std::vector<char> buffer(1 << 20);
  bool ok = true;
  size_t n;
  while (ok && (n = std::fread(buffer.data(), 1, buffer.size(), in)) > 0) {
    ok = gzwrite(out, buffer.data(), static_cast<unsigned>(n)) ==
         static_cast<int>(n);
  }
  ok = ok && !std::ferror(in);
  std::fclose(in);
  ok = (gzclose(out) == Z_OK) && ok;
  return ok ? absl::OkStatus() : absl::InternalError("gzip failed");
}

template <typename T>
absl::Status WriteVolumeImpl(const Volume<T>& volume, const std::string& path) {
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

  using ImageType = itk::Image<T, 3>;
  const Grid& grid = volume.grid;
  typename ImageType::Pointer image = ImageType::New();
  typename ImageType::SizeType size;
  typename ImageType::SpacingType spacing;
  typename ImageType::PointType origin;
  typename ImageType::DirectionType direction;
  for (int a = 0; a < 3; ++a) {
    size[a] = static_cast<itk::SizeValueType>(grid.size[a]);
    spacing[a] = grid.spacing[a];
    origin[a] = grid.origin[a];
    for (int c = 0; c < 3; ++c) direction(a, c) = grid.direction[3 * a + c];
  }
  image->SetRegions(typename ImageType::RegionType(size));
  image->SetSpacing(spacing);
  image->SetOrigin(origin);
  image->SetDirection(direction);
  // Writers only read the buffer: wrap the volume's memory without a copy.
  auto container = ImageType::PixelContainer::New();
  container->SetImportPointer(const_cast<T*>(volume.data.data()),
                              volume.data.size(),
                              /*LetContainerManageMemory=*/false);
  image->SetPixelContainer(container);

  // NIfTI's own gzip ignores ITK's compression level and is slow on float
  // volumes that barely compress (267 of 312 MB on the CT phantom), so a
  // .nii.gz is written as .nii by ITK and then gzipped by zlib at level 1:
  // the same file format (a .nii.gz is a gzip stream of the .nii).
  const bool gzip_nifti = info->extension == ".nii.gz";
  FormatInfo itk_info = *info;
  if (gzip_nifti) itk_info.extension = ".nii";
  const std::string temp = TemporaryPath(
      gzip_nifti ? path.substr(0, path.size() - 3) : path, itk_info);
  if (absl::Status created = CreateEmptyFile(temp); !created.ok()) {
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", created.message()));
  }
  std::error_code ec;
  try {
    auto writer = itk::ImageFileWriter<ImageType>::New();
    auto io = MakeImageIO(info->format);
    // zlib's fastest level (NRRD): float distance fields gain little from
    // harder compression, which made writing the largest stage of a job.
    io->SetCompressionLevel(1);
    writer->SetImageIO(io);
    writer->SetFileName(temp);
    writer->SetInput(image);
    writer->SetUseCompression(itk_info.extension == ".nrrd");
    writer->Update();
  } catch (const std::exception& e) {
    std::filesystem::remove(temp, ec);
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", e.what()));
  }
  std::string final_temp = temp;
  if (gzip_nifti) {
    final_temp = temp + ".gz";
    const absl::Status gz = GzipFile(temp, final_temp);
    std::filesystem::remove(temp, ec);
    if (!gz.ok()) {
      std::filesystem::remove(final_temp, ec);
      return absl::InternalError(
          absl::StrCat("cannot write ", path, ": ", gz.message()));
    }
  }
  std::filesystem::rename(final_temp, path, ec);
  if (ec) {
    const std::string reason = ec.message();
    std::filesystem::remove(final_temp, ec);
    return absl::InternalError(
        absl::StrCat("cannot write ", path, ": ", reason));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status WriteVolume(const Volume<float>& volume, const std::string& path) {
  return WriteVolumeImpl(volume, path);
}

absl::Status WriteVolume(const Volume<uint8_t>& volume,
                         const std::string& path) {
  return WriteVolumeImpl(volume, path);
}

absl::Status WriteVolume(const Volume<uint16_t>& volume,
                         const std::string& path) {
  return WriteVolumeImpl(volume, path);
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
