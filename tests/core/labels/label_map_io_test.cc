// Label maps in any index layout of the reference's voxels (issue 24): read
// exactly, filled exactly as in the reference's layout, written back in the
// input's layout and header.
#include "core/labels/label_map_io.h"

#include <unistd.h>

#include <array>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "core/dicom/series_reader.h"
#include "core/labels/fill_job.h"
#include "core/labels/label_fill.h"
#include "core/volume_io/volume_io.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/testing/paths.h"

namespace interslice {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

// A reference grid with a different size and spacing on every axis, so that
// a wrong permutation cannot pass.
Grid Reference() {
  Grid g;
  g.size = {30, 26, 13};
  g.spacing = {0.8, 0.9, 2.5};
  g.origin = {-12, 7, 30};
  return g;
}

// Two touching labels on every 3rd slice (0, 3, ..., 12), an ellipse whose
// size and centre change with the slice, split at a column; every label
// pixel is at a distinct (i, j, k) pattern, so any misplaced voxel shows.
LabelVolume KeySlices(const Grid& g) {
  LabelVolume v;
  v.grid = g;
  v.data.assign(g.VoxelCount(), 0);
  for (int64_t k = 0; k < g.size[2]; k += 3) {
    const double cx = 12 + 0.5 * k, cy = 11 + 0.3 * k, r = 5 + 0.4 * k;
    for (int64_t j = 0; j < g.size[1]; ++j) {
      for (int64_t i = 0; i < g.size[0]; ++i) {
        const double x = (i - cx) / r, y = (j - cy) / (0.7 * r);
        if (x * x + y * y <= 1) v.at(i, j, k) = i < cx + 1 ? 1 : 2;
      }
    }
  }
  return v;
}

struct Layout {
  const char* name;
  std::array<int, 3> axis;
  std::array<bool, 3> flipped;
};

// nibabel / dcm2niix style (RAS: i and j flipped), rows flipped, slices
// flipped, permuted axes, permuted and flipped.
const Layout kLayouts[] = {
    {"same", {0, 1, 2}, {false, false, false}},
    {"rows-flipped", {0, 1, 2}, {false, true, false}},
    {"ras", {0, 1, 2}, {true, true, false}},
    {"slices-flipped", {0, 1, 2}, {false, false, true}},
    {"permuted", {2, 0, 1}, {false, false, false}},
    {"permuted-flipped", {1, 2, 0}, {true, false, true}},
};

// The file grid of `layout` on `ref`, built from the definition: file axis a
// runs along reference axis axis[a] (reversed when flipped), and its first
// voxel is the reference voxel at index 0 or n - 1 of that axis.
Grid FileGrid(const Grid& ref, const Layout& layout) {
  Grid f;
  Vec3 first = {0, 0, 0};
  for (int a = 0; a < 3; ++a) {
    const int b = layout.axis[a];
    f.size[a] = ref.size[b];
    f.spacing[a] = ref.spacing[b];
    const Vec3 axis = ref.Axis(b);
    for (int c = 0; c < 3; ++c) {
      f.direction[3 * c + a] = layout.flipped[a] ? -axis[c] : axis[c];
    }
    first[b] = layout.flipped[a] ? static_cast<double>(ref.size[b] - 1) : 0;
  }
  f.origin = ref.IndexToPhysical(first);
  return f;
}

// `v` (on the reference) in the file layout, voxel by voxel.
LabelVolume InFileLayout(const LabelVolume& v, const Layout& layout) {
  LabelVolume out;
  out.grid = FileGrid(v.grid, layout);
  out.data.resize(v.data.size());
  for (int64_t c = 0; c < out.grid.size[2]; ++c) {
    for (int64_t b = 0; b < out.grid.size[1]; ++b) {
      for (int64_t a = 0; a < out.grid.size[0]; ++a) {
        const int64_t f[3] = {a, b, c};
        int64_t r[3];
        for (int d = 0; d < 3; ++d) {
          const int ax = layout.axis[d];
          r[ax] = layout.flipped[d] ? v.grid.size[ax] - 1 - f[d] : f[d];
        }
        out.at(a, b, c) = v.at(r[0], r[1], r[2]);
      }
    }
  }
  return out;
}

void ExpectSameGrid(const Grid& a, const Grid& b, const std::string& what) {
  EXPECT_EQ(a.size, b.size) << what;
  for (int n = 0; n < 3; ++n) {
    EXPECT_NEAR(a.spacing[n], b.spacing[n], 1e-5) << what;
    EXPECT_NEAR(a.origin[n], b.origin[n], 1e-4) << what;
  }
  for (int e = 0; e < 9; ++e) {
    EXPECT_NEAR(a.direction[e], b.direction[e], 1e-6) << what;
  }
}

class LabelMapIoTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("interslice_label_map_io_test_" + std::to_string(getpid()) + "_" +
            ::testing::UnitTest::GetInstance()->current_test_info()->name());
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string Path(const std::string& name) const {
    return (dir_ / name).string();
  }
  fs::path dir_;
};

absl::StatusOr<FillResult> Fill(const LabelVolume& labels, int factor) {
  FillOptions options;
  options.method = FillMethod::kSolver;
  options.solver.method = SolverMethod::kLinear;
  if (factor > 1) options.z_resolution.factor = factor;
  return FillBetweenSlices(labels, options, ComputeContext{.threads = 1});
}

// Every layout, in NIfTI (.nii.gz and .nii, with the qform or the sform as
// the transform) and NRRD: read onto the reference exactly, filled exactly
// as the same map in the reference's layout, written back in the file's
// layout, header codes and voxel type; with an insertion factor of 2 the
// slice axis of the file gets the new slices wherever it is.
TEST_F(LabelMapIoTest, EveryLayoutFillsAsTheReferenceLayoutAndComesBackInIt) {
  const Grid ref = Reference();
  const LabelVolume keys = KeySlices(ref);
  for (int factor : {1, 2}) {
    absl::StatusOr<FillResult> expected = Fill(keys, factor);
    ASSERT_TRUE(expected.ok()) << expected.status();
    ASSERT_GT(expected->labels.data.size(), keys.data.size() * (factor - 1));
    for (const Layout& layout : kLayouts) {
      for (const char* ext : {".nii.gz", ".nii", ".nrrd"}) {
        const std::string what =
            absl::StrCat(layout.name, ext, " factor ", factor);
        const bool nifti = std::string(ext) != ".nrrd";
        const LabelVolume file = InFileLayout(keys, layout);
        // qform only (sform code 0) for .nii, sform only (qform code 0)
        // for .nii.gz; the NRRD with a key/value field; uint8 for .nii.
        VolumeHeaderFields fields;
        if (std::string(ext) == ".nii") {
          fields.qform_code = 1;
          fields.sform_code = 0;
        } else if (nifti) {
          fields.qform_code = 0;
          fields.sform_code = 2;
        } else {
          fields.key_values = {{"Segment0_Name", "left"},
                               {"Segment0_Extent", "0 1 0 1 0 1"}};
        }
        const std::string in =
            Path(absl::StrCat("in-", layout.name, "-", factor, ext));
        if (std::string(ext) == ".nii") {
          Volume<uint8_t> narrow;
          narrow.grid = file.grid;
          narrow.data.assign(file.data.begin(), file.data.end());
          ASSERT_TRUE(WriteVolume(narrow, in, fields).ok()) << what;
        } else {
          ASSERT_TRUE(WriteVolume(file, in, fields).ok()) << what;
        }

        absl::StatusOr<LabelMapOnReference> read =
            ReadLabelMapOnReference(in, ref);
        ASSERT_TRUE(read.ok()) << what << ": " << read.status();
        EXPECT_EQ(read->labels.data, keys.data) << what;
        EXPECT_EQ(read->file.mapping.IsIdentity(),
                  std::string(layout.name) == "same")
            << what;
        absl::StatusOr<FillResult> filled = Fill(read->labels, factor);
        ASSERT_TRUE(filled.ok()) << what << ": " << filled.status();
        EXPECT_EQ(filled->labels.data, expected->labels.data) << what;

        const std::string out =
            Path(absl::StrCat("out-", layout.name, "-", factor, ext));
        ASSERT_TRUE(WriteLabelMapLike(filled->labels, read->file, out).ok())
            << what;
        absl::StatusOr<VolumeFileHeader> header = ReadVolumeFileHeader(out);
        ASSERT_TRUE(header.ok()) << what << ": " << header.status();
        // The file's layout: its directions and first voxel, its slice axis
        // (wherever it is) with factor x the slices over the same extent.
        Grid want = file.grid;
        for (int a = 0; a < 3; ++a) {
          if (layout.axis[a] == 2) {
            want.size[a] = (want.size[a] - 1) * factor + 1;
            want.spacing[a] /= factor;
          }
        }
        ExpectSameGrid(header->grid, want, what);
        if (nifti) {
          EXPECT_EQ(header->qform_code, *fields.qform_code) << what;
          EXPECT_EQ(header->sform_code, *fields.sform_code) << what;
          EXPECT_EQ(header->component_type, std::string(ext) == ".nii"
                                                ? "unsigned_char"
                                                : "unsigned_short")
              << what;
        } else {
          ASSERT_EQ(header->key_values.size(), 1u) << what;
          EXPECT_EQ(header->key_values[0].first, "Segment0_Name") << what;
        }
        absl::StatusOr<Volume<float>> back = ReadVolumeAsFloat(out);
        ASSERT_TRUE(back.ok()) << what;
        const LabelVolume want_data = InFileLayout(filled->labels, layout);
        ASSERT_EQ(back->data.size(), want_data.data.size()) << what;
        bool same = true;
        for (size_t n = 0; n < want_data.data.size() && same; ++n) {
          same = back->data[n] == want_data.data[n];
        }
        EXPECT_TRUE(same) << what;
      }
    }
  }
}

// A NRRD in RAS space, written as another tool would (hand-made header):
// "space: right-anterior-superior" with i and j running to the patient's
// right and front, i.e. along -x and -y of LPS.
TEST_F(LabelMapIoTest, NrrdInRasSpaceIsReadOntoTheLpsReference) {
  const Grid ref = Reference();
  const LabelVolume keys = KeySlices(ref);
  const Layout ras = {"ras", {0, 1, 2}, {true, true, false}};
  const LabelVolume file = InFileLayout(keys, ras);
  // LPS origin (x, y, z) is RAS (-x, -y, z); the RAS directions of file
  // axes flipped in LPS are +1.
  const std::string path = Path("ras.nrrd");
  {
    std::ofstream out(path, std::ios::binary);
    out << "NRRD0004\ntype: unsigned short\ndimension: 3\n"
        << "space: right-anterior-superior\n"
        << absl::StrFormat("sizes: %d %d %d\n", ref.size[0], ref.size[1],
                           ref.size[2])
        << absl::StrFormat("space directions: (%g,0,0) (0,%g,0) (0,0,%g)\n",
                           ref.spacing[0], ref.spacing[1], ref.spacing[2])
        << "kinds: domain domain domain\nendian: little\nencoding: raw\n"
        << absl::StrFormat("space origin: (%g,%g,%g)\n\n", -file.grid.origin[0],
                           -file.grid.origin[1], file.grid.origin[2]);
    out.write(reinterpret_cast<const char*>(file.data.data()),
              file.data.size() * 2);
  }
  absl::StatusOr<LabelMapOnReference> read = ReadLabelMapOnReference(path, ref);
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(read->file.header.nrrd_space, "right-anterior-superior");
  EXPECT_EQ(read->file.mapping.Describe(), "(-i, -j, k)");
  EXPECT_EQ(read->labels.data, keys.data);
}

TEST_F(LabelMapIoTest, MapsOffTheReferenceVoxelsAreRefusedSayingByHowMuch) {
  const Grid ref = Reference();
  const LabelVolume keys = KeySlices(ref);
  const Layout permuted = {"permuted", {2, 0, 1}, {false, false, false}};
  struct Case {
    std::string name;
    Grid grid;
    std::string message;
  };
  std::vector<Case> cases;
  // Shifted by half a slice (1.25 mm) along the reference's slice axis,
  // which is file axis 0 of the permuted layout.
  Grid shifted = FileGrid(ref, permuted);
  shifted.origin[2] += 1.25;
  cases.push_back({"shifted.nii.gz", shifted,
                   "1.250 mm off the reference series' along its slice axis "
                   "(k)"});
  Grid shifted_rows = FileGrid(ref, kLayouts[2]);
  shifted_rows.origin[1] -= 0.3;
  cases.push_back({"rows.nrrd", shifted_rows,
                   "0.300 mm off the reference series' along its row axis "
                   "(j)"});
  Grid tilted = ref;
  const double c = std::cos(0.2), s = std::sin(0.2);
  tilted.direction = {c, -s, 0, s, c, 0, 0, 0, 1};
  cases.push_back({"tilted.nii.gz", tilted, "tilted 11.46 degrees"});
  Grid thin = ref;
  thin.spacing[2] = 2.0;
  cases.push_back({"thin.nrrd", thin, "spacing 2 mm along its axis 2"});
  for (const Case& c : cases) {
    LabelVolume v = keys;
    v.grid = c.grid;
    ASSERT_TRUE(WriteVolume(v, Path(c.name)).ok()) << c.name;
    absl::StatusOr<LabelMapOnReference> read =
        ReadLabelMapOnReference(Path(c.name), ref);
    ASSERT_FALSE(read.ok()) << c.name;
    EXPECT_EQ(read.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(read.status().message(), HasSubstr(c.message)) << c.name;
    EXPECT_EQ(std::string(read.status().message()).find('\n'),
              std::string::npos);
  }
  // Fewer slices: named with both sizes.
  LabelVolume short_map = keys;
  short_map.grid.size[2] -= 1;
  short_map.data.resize(short_map.grid.VoxelCount());
  ASSERT_TRUE(WriteVolume(short_map, Path("short.nrrd")).ok());
  EXPECT_THAT(
      ReadLabelMapOnReference(Path("short.nrrd"), ref).status().message(),
      HasSubstr("the label map is 30 x 26 x 12 voxels"));
  // A fraction is not a label.
  Volume<float> fractional;
  fractional.grid = ref;
  fractional.data.assign(ref.VoxelCount(), 0.0f);
  fractional.data[31] = 0.5f;
  ASSERT_TRUE(WriteVolume(fractional, Path("fraction.nrrd")).ok());
  EXPECT_THAT(
      ReadLabelMapOnReference(Path("fraction.nrrd"), ref).status().message(),
      HasSubstr("holds 0.5"));
  // Scaled values (NIfTI scl_slope 2).
  ASSERT_TRUE(WriteVolume(keys, Path("scaled.nii")).ok());
  {
    std::fstream f(Path("scaled.nii"),
                   std::ios::in | std::ios::out | std::ios::binary);
    const float slope = 2;
    f.seekp(112);
    f.write(reinterpret_cast<const char*>(&slope), 4);
  }
  EXPECT_THAT(
      ReadLabelMapOnReference(Path("scaled.nii"), ref).status().message(),
      HasSubstr("scl_slope 2"));
}

// What a user's tools see: nibabel (Debian's python3-nibabel, installed by
// scripts/install-deps.sh; missing, the test fails: it must not pass
// without testing) reads the written map with the affine,
// transform codes, shape and voxel type of the input.
TEST_F(LabelMapIoTest, NibabelSeesTheInputsHeaderInTheOutput) {
  if (std::system("/usr/bin/python3 -c 'import nibabel' >/dev/null 2>&1") !=
      0) {
    FAIL() << "python3-nibabel is not installed (scripts/install-deps.sh "
              "installs it); this test needs it";
  }
  const Grid ref = Reference();
  const LabelVolume keys = KeySlices(ref);
  const Layout ras = {"ras", {0, 1, 2}, {true, true, false}};
  const LabelVolume file = InFileLayout(keys, ras);
  const std::string in = Path("in.nii.gz"), out = Path("out.nii.gz");
  Volume<uint8_t> narrow;
  narrow.grid = file.grid;
  narrow.data.assign(file.data.begin(), file.data.end());
  VolumeHeaderFields fields;
  // Not ITK's own codes (1, 1), so that they must be carried over.
  fields.qform_code = 2;
  fields.sform_code = 0;
  ASSERT_TRUE(WriteVolume(narrow, in, fields).ok());
  absl::StatusOr<LabelMapOnReference> read = ReadLabelMapOnReference(in, ref);
  ASSERT_TRUE(read.ok()) << read.status();
  absl::StatusOr<FillResult> filled = Fill(read->labels, 1);
  ASSERT_TRUE(filled.ok());
  ASSERT_TRUE(WriteLabelMapLike(filled->labels, read->file, out).ok());
  const std::string script = Path("describe.py");
  std::ofstream(script)
      << "import sys, nibabel, numpy\n"
         "for p in sys.argv[1:]:\n"
         "    im = nibabel.load(p)\n"
         "    h = im.header\n"
         "    print(numpy.round(im.affine, 4).tolist(), int(h['qform_code']),\n"
         "          int(h['sform_code']), im.shape, h.get_data_dtype().name,\n"
         "          nibabel.aff2axcodes(im.affine))\n";
  const std::string listing = Path("listing.txt");
  ASSERT_EQ(std::system(absl::StrCat("/usr/bin/python3 ", script, " ", in, " ",
                                     out, " > ", listing)
                            .c_str()),
            0);
  std::ifstream lines(listing);
  std::string a, b;
  ASSERT_TRUE(std::getline(lines, a));
  ASSERT_TRUE(std::getline(lines, b));
  EXPECT_EQ(a, b);
  // RAS+ as nibabel names it: i to the right... as the input had it.
  EXPECT_THAT(b, HasSubstr("('R', 'A', 'S')"));
  EXPECT_THAT(b, HasSubstr("uint8"));
}

// The whole job on a real DICOM reference (4 slices of the thick CT
// phantom): a label map with rows and columns flipped (nibabel's RAS
// layout) fills as the same map in the reference's layout, and
// labels.nii.gz comes back in the input's layout.
TEST_F(LabelMapIoTest, FillJobKeepsTheInputLayout) {
  const std::string reference =
      std::string(::interslice::testing::TestDataDir()) + "/ct-thick";
  absl::StatusOr<DicomSeries> series = ReadDicomSeries({reference}, {}, {});
  ASSERT_TRUE(series.ok()) << series.status();
  const Grid ref = series->image.grid;
  ASSERT_EQ(ref.size[2], 4);
  // Two touching labels drawn on slices 0 and 3, moving between them.
  LabelVolume keys;
  keys.grid = ref;
  keys.data.assign(ref.VoxelCount(), 0);
  for (int64_t k : {0, 3}) {
    for (int64_t j = 200; j < 260 + 10 * k; ++j) {
      for (int64_t i = 180 + 5 * k; i < 300; ++i) {
        keys.at(i, j, k) = i < 240 ? 1 : 2;
      }
    }
  }
  const Layout ras = {"ras", {0, 1, 2}, {true, true, false}};
  const LabelVolume file = InFileLayout(keys, ras);
  ASSERT_TRUE(WriteVolume(keys, Path("same.nii.gz")).ok());
  ASSERT_TRUE(WriteVolume(file, Path("ras.nii.gz")).ok());
  FillJobSpec spec;
  spec.reference = {reference};
  spec.mesh_formats = {};
  spec.volume_formats = {"nii", "nrrd"};
  spec.fill.method = FillMethod::kSolver;
  spec.fill.solver.method = SolverMethod::kLinear;
  spec.segmentation = Path("same.nii.gz");
  spec.output_dir = Path("same");
  absl::StatusOr<FillJobReport> same = RunFillJob(spec, {});
  ASSERT_TRUE(same.ok()) << same.status();
  EXPECT_EQ(same->input_layout, "(i, j, k)");
  spec.segmentation = Path("ras.nii.gz");
  spec.output_dir = Path("ras");
  absl::StatusOr<FillJobReport> flipped = RunFillJob(spec, {});
  ASSERT_TRUE(flipped.ok()) << flipped.status();
  EXPECT_EQ(flipped->input_layout, "(-i, -j, k)");
  for (const char* name : {"labels.nii.gz", "labels.nrrd"}) {
    absl::StatusOr<Volume<float>> a =
        ReadVolumeAsFloat(Path(absl::StrCat("same/", name)));
    absl::StatusOr<Volume<float>> b =
        ReadVolumeAsFloat(Path(absl::StrCat("ras/", name)));
    ASSERT_TRUE(a.ok() && b.ok()) << name;
    ExpectSameGrid(b->grid, file.grid, name);
    LabelVolume filled;
    filled.grid = ref;
    filled.data.assign(a->data.begin(), a->data.end());
    const LabelVolume want = InFileLayout(filled, ras);
    ASSERT_EQ(b->data.size(), want.data.size());
    int64_t differ = 0, labelled = 0;
    for (size_t n = 0; n < want.data.size(); ++n) {
      differ += b->data[n] != want.data[n];
      labelled += want.data[n] != 0;
    }
    EXPECT_EQ(differ, 0) << name;
    // Slices 1 and 2 were filled.
    EXPECT_GT(labelled, 2 * 60 * 120) << name;
  }
}

}  // namespace
}  // namespace interslice
