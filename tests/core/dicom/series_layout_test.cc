// The stack layout on its own (core/dicom/series_layout.h): headers made in
// memory, so each rule of the contract is checked without writing files.
#include "core/dicom/series_layout.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace interslice {
namespace {

using dicom_internal::FileHeader;
using dicom_internal::FileKind;
using dicom_internal::FrameGeometry;
using ::testing::AllOf;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::Not;

constexpr std::array<double, 6> kAxial = {1, 0, 0, 0, 1, 0};
constexpr double kPi = 3.14159265358979323846;

// A 5 x 4 (columns x rows) CT slice at `position`; PixelSpacing 0.5 mm
// between rows, 0.25 mm between columns.
FileHeader Slice(const std::string& path, const Vec3& position,
                 const std::array<double, 6>& orientation = kAxial) {
  FileHeader h;
  h.path = "/some/patient folder/" + path;
  h.kind = FileKind::kImage;
  h.series_uid = "1.2.3";
  h.frame_of_reference_uid = "1.2.3.4.5";
  h.modality = "CT";
  h.rows = 4;
  h.columns = 5;
  h.orientation = orientation;
  h.position = position;
  h.pixel_spacing = {0.5, 0.25};
  return h;
}

std::vector<size_t> All(const std::vector<FileHeader>& headers) {
  std::vector<size_t> members(headers.size());
  for (size_t i = 0; i < members.size(); ++i) members[i] = i;
  return members;
}

absl::StatusOr<DicomStackLayout> LayOut(const std::vector<FileHeader>& headers,
                                        const std::string& volume = "") {
  return LayOutDicomStack(headers, All(headers), volume);
}

Vec3 Add(const Vec3& a, const Vec3& b) {
  return {a[0] + b[0], a[1] + b[1], a[2] + b[2]};
}
Vec3 Times(const Vec3& a, double s) { return {a[0] * s, a[1] * s, a[2] * s}; }
double Dot(const Vec3& a, const Vec3& b) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

TEST(LayOutDicomStackTest, SortsAlongAnObliqueNormalAndBuildsTheGrid) {
  // Rows along +x, columns along (0, cos 30, -sin 30): the normal row x col
  // is (0, sin 30, cos 30).
  const double c = std::cos(kPi / 6), s = std::sin(kPi / 6);
  const std::array<double, 6> oblique = {1, 0, 0, 0, c, -s};
  const Vec3 normal = {0, s, c};
  const Vec3 origin = {-10, 20, 30};
  // Given out of order; "b" is the lowest along the normal.
  const std::vector<FileHeader> headers = {
      Slice("a.dcm", Add(origin, Times(normal, 3)), oblique),
      Slice("b.dcm", origin, oblique),
      Slice("c.dcm", Add(origin, Times(normal, 1.5)), oblique)};
  const auto stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  ASSERT_EQ(stack->order.size(), 3u);
  EXPECT_EQ(stack->order[0].header, 1u);
  EXPECT_EQ(stack->order[1].header, 2u);
  EXPECT_EQ(stack->order[2].header, 0u);
  const double p0 = Dot(origin, normal);
  EXPECT_NEAR(stack->positions[0], p0, 1e-9);
  EXPECT_NEAR(stack->positions[1], p0 + 1.5, 1e-9);
  EXPECT_NEAR(stack->positions[2], p0 + 3, 1e-9);

  const Grid& grid = stack->grid;
  EXPECT_THAT(grid.size, ElementsAre(5, 4, 3));
  // PixelSpacing is (between rows, between columns): i steps 0.25 mm.
  EXPECT_DOUBLE_EQ(grid.spacing[0], 0.25);
  EXPECT_DOUBLE_EQ(grid.spacing[1], 0.5);
  EXPECT_NEAR(grid.spacing[2], 1.5, 1e-9);
  EXPECT_EQ(grid.origin, origin);
  for (int r = 0; r < 3; ++r) {
    EXPECT_NEAR(grid.direction[3 * r + 0], oblique[r], 1e-12);
    EXPECT_NEAR(grid.direction[3 * r + 1], oblique[3 + r], 1e-12);
    EXPECT_NEAR(grid.direction[3 * r + 2], normal[r], 1e-12);
  }
  EXPECT_TRUE(stack->uniform);
  EXPECT_TRUE(stack->tilt_shift.empty());
  EXPECT_EQ(stack->tilt_degrees, 0);
}

TEST(LayOutDicomStackTest, SpacingIsTheMedianGapAndReportsAMissingSlice) {
  // Gaps 2, 2, 4, 2 (the slice at 6 is missing): median 2, not uniform.
  std::vector<FileHeader> headers;
  for (double z : {0.0, 2.0, 4.0, 8.0, 10.0}) {
    headers.push_back(Slice("z" + std::to_string(z), {0, 0, z}));
  }
  const auto stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_DOUBLE_EQ(stack->grid.spacing[2], 2);
  EXPECT_DOUBLE_EQ(stack->min_gap, 2);
  EXPECT_DOUBLE_EQ(stack->max_gap, 4);
  EXPECT_FALSE(stack->uniform);
}

TEST(LayOutDicomStackTest, GapsWithinOnePercentOfTheMedianAreUniform) {
  // Gaps 2, 2.015, 1.985: within max(0.01 mm, 1% of 2 mm) of the median.
  std::vector<FileHeader> headers;
  for (double z : {0.0, 2.0, 4.015, 6.0}) {
    headers.push_back(Slice("z" + std::to_string(z), {0, 0, z}));
  }
  auto stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_TRUE(stack->uniform);
  EXPECT_DOUBLE_EQ(stack->grid.spacing[2], 2);

  // 2.03 is 1.5% off: not uniform any more.
  headers[2].position[2] = 4.03;
  stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_FALSE(stack->uniform);
}

TEST(LayOutDicomStackTest, OneSliceTakesItsThicknessThenSpacingBetweenSlices) {
  FileHeader h = Slice("only.dcm", {1, 2, 3});
  h.slice_thickness = 2.5;
  h.spacing_between_slices = 4;
  auto stack = LayOut({h});
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_DOUBLE_EQ(stack->grid.spacing[2], 2.5);
  EXPECT_EQ(stack->min_gap, 0);
  EXPECT_EQ(stack->max_gap, 0);

  h.slice_thickness = 0;
  stack = LayOut({h});
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_DOUBLE_EQ(stack->grid.spacing[2], 4);

  h.spacing_between_slices = 0;
  stack = LayOut({h});
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_DOUBLE_EQ(stack->grid.spacing[2], 1);
}

TEST(LayOutDicomStackTest, SlicesAtTheSamePositionNameBothByBaseName) {
  const auto stack =
      LayOut({Slice("a.dcm", {0, 0, 0}), Slice("b.dcm", {0, 0, 0.0005}),
              Slice("c.dcm", {0, 0, 2})});
  EXPECT_EQ(stack.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(stack.status().message(),
              AllOf(HasSubstr("a.dcm and b.dcm are at the same slice "
                              "position"),
                    Not(HasSubstr("patient folder"))));
}

TEST(LayOutDicomStackTest, TiltShiftsAreInPixelsAlongRowsAndColumns) {
  // Each slice 2 mm further along z and 0.5 mm further along y (one row):
  // the stack leans by atan(0.5 / 2) against the normal.
  std::vector<FileHeader> headers;
  for (int k = 0; k < 4; ++k) {
    headers.push_back(Slice("t" + std::to_string(k), {0, 0.5 * k, 2.0 * k}));
  }
  const auto stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  ASSERT_EQ(stack->tilt_shift.size(), 4u);
  for (int k = 0; k < 4; ++k) {
    EXPECT_NEAR(stack->tilt_shift[k][0], 0, 1e-12) << k;
    EXPECT_NEAR(stack->tilt_shift[k][1], k, 1e-12) << k;
  }
  EXPECT_NEAR(stack->tilt_degrees, std::atan(0.25) * 180 / kPi, 1e-9);
  // The grid stays orthogonal, along the slices' normal.
  EXPECT_NEAR(stack->grid.direction[8], 1, 1e-12);
  EXPECT_NEAR(stack->grid.spacing[2], 2, 1e-12);
}

TEST(LayOutDicomStackTest, InPlaneDriftBelowTheToleranceIsNoTilt) {
  // 0.005 mm in-plane per mm along the normal: below 0.01.
  const auto stack = LayOut({Slice("a", {0, 0, 0}), Slice("b", {0, 0.01, 2}),
                             Slice("c", {0, 0.02, 4})});
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_TRUE(stack->tilt_shift.empty());
  EXPECT_EQ(stack->tilt_degrees, 0);
}

TEST(LayOutDicomStackTest, SlicesThatDoNotOverlapAreNotAStack) {
  // The third slice is 5 columns (1.25 mm) to the side: a whole image.
  const auto stack =
      LayOut({Slice("a.dcm", {0, 0, 0}), Slice("b.dcm", {0.5, 0, 2}),
              Slice("c.dcm", {1.25, 0, 4})});
  EXPECT_EQ(stack.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(stack.status().message(),
              AllOf(HasSubstr("c.dcm is offset by (5.0, 0.0) pixels"),
                    HasSubstr("do not overlap")));
}

TEST(LayOutDicomStackTest, TheFirstBrokenMemberFailsTheLayout) {
  std::vector<FileHeader> headers = {Slice("a.dcm", {0, 0, 0}),
                                     Slice("b.dcm", {0, 0, 1}),
                                     Slice("c.dcm", {0, 0, 2})};
  headers[1].problem = absl::InvalidArgumentError("b.dcm: broken");
  headers[2].problem = absl::UnimplementedError("c.dcm: colour");
  EXPECT_EQ(LayOutDicomStack(headers, {0, 1, 2}, "").status().message(),
            "b.dcm: broken");
  EXPECT_EQ(LayOutDicomStack(headers, {2, 1, 0}, "").status().code(),
            absl::StatusCode::kUnimplemented);
  // A broken file outside the members does not matter.
  EXPECT_TRUE(LayOutDicomStack(headers, {0}, "").ok());
}

TEST(LayOutDicomStackTest, NoMembersIsAnError) {
  const auto stack = LayOutDicomStack({Slice("a.dcm", {0, 0, 0})}, {}, "");
  EXPECT_EQ(stack.status().code(), absl::StatusCode::kInvalidArgument);
}

// One enhanced multi-frame file: frames 0 and 2 of volume "A", 1 and 3 of
// volume "B", at the same two positions, each with its own rescale.
FileHeader TwoVolumeFile() {
  FileHeader h = Slice("enh.dcm", {0, 0, 0});
  for (int f = 0; f < 4; ++f) {
    FrameGeometry g;
    g.position = {0, 0, f < 2 ? 7.0 : 3.0};
    g.orientation = kAxial;
    g.pixel_spacing = {0.5, 0.25};
    g.rescale_slope = 1 + f;
    g.rescale_intercept = -10.0 * f;
    g.volume = f % 2 == 0 ? "A" : "B";
    h.frames.push_back(g);
  }
  return h;
}

TEST(LayOutDicomStackTest, VolumesOfMultiFrameFilesAreListedAndChosen) {
  const std::vector<FileHeader> headers = {TwoVolumeFile()};
  const auto none = LayOut(headers);
  EXPECT_EQ(none.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(none.status().message(),
              AllOf(HasSubstr("2 volumes"), HasSubstr("\"A\" (2 slices)"),
                    HasSubstr("\"B\" (2 slices)")));

  const auto b = LayOut(headers, "B");
  ASSERT_TRUE(b.ok()) << b.status();
  ASSERT_EQ(b->order.size(), 2u);
  // Sorted along z: frame 3 (z 3) before frame 1 (z 7), each with the
  // geometry and rescale of its own frame.
  EXPECT_EQ(b->order[0].frame, 3);
  EXPECT_EQ(b->order[1].frame, 1);
  EXPECT_EQ(b->order[0].rescale_slope, 4);
  EXPECT_EQ(b->order[0].rescale_intercept, -30);
  EXPECT_EQ(b->order[1].volume, "B");
  EXPECT_DOUBLE_EQ(b->grid.spacing[2], 4);
  EXPECT_EQ(b->grid.origin, (Vec3{0, 0, 3}));

  const auto missing = LayOut(headers, "C");
  EXPECT_EQ(missing.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(missing.status().message(),
              AllOf(HasSubstr("volume \"C\" is not in the series"),
                    HasSubstr("\"A\" (2 slices)")));
}

TEST(LayOutDicomStackTest, FramesOfOneVolumeAreNamedWithTheirFrame) {
  FileHeader h = TwoVolumeFile();
  h.frames[3].position = h.frames[1].position;  // two "B" frames at z 7
  const auto stack = LayOut({h}, "B");
  EXPECT_EQ(stack.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(stack.status().message(),
              HasSubstr("enh.dcm frame 2 and enh.dcm frame 4 are at the same "
                        "slice position"));
}

TEST(LayOutDicomStackTest, AnOddFrameOfReferenceIsNamedWithoutItsUid) {
  std::vector<FileHeader> headers = {Slice("a.dcm", {0, 0, 0}),
                                     Slice("b.dcm", {0, 0, 1}),
                                     Slice("c.dcm", {0, 0, 2})};
  headers[1].frame_of_reference_uid = "9.8.7.6";
  const auto stack = LayOutDicomStack(headers, All(headers), "",
                                      /*strict_frame_of_reference=*/true);
  EXPECT_EQ(stack.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(
      stack.status().message(),
      AllOf(HasSubstr("inconsistent FrameOfReferenceUID: b.dcm has a "
                      "different one from 2 of the 3 slices (e.g. a.dcm)"),
            Not(HasSubstr("9.8.7.6")), Not(HasSubstr("1.2.3.4.5")),
            Not(HasSubstr("values in all"))));
}

// Issue 42: with every UID different, the message said "b.dcm has a
// different one from 1 of the 3 slices": no slice is the odd one out.
TEST(LayOutDicomStackTest, FramesOfReferenceAllDifferentAreCountedRight) {
  std::vector<FileHeader> headers = {Slice("a.dcm", {0, 0, 0}),
                                     Slice("b.dcm", {0, 0, 1}),
                                     Slice("c.dcm", {0, 0, 2})};
  headers[1].frame_of_reference_uid = "9.8.7.6";
  headers[2].frame_of_reference_uid = "9.8.7.7";
  const auto strict = LayOutDicomStack(headers, All(headers), "",
                                       /*strict_frame_of_reference=*/true);
  EXPECT_EQ(strict.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(strict.status().message(),
              AllOf(HasSubstr("inconsistent FrameOfReferenceUID: each of the "
                              "3 slices has a different one (e.g. a.dcm and "
                              "b.dcm differ)"),
                    Not(HasSubstr("1 of the 3")), Not(HasSubstr("9.8.7"))));
  // Three values, one of them shared: the majority, and how many values.
  headers.push_back(Slice("d.dcm", {0, 0, 3}));
  const auto three = LayOutDicomStack(headers, All(headers), "",
                                      /*strict_frame_of_reference=*/true);
  EXPECT_THAT(three.status().message(),
              HasSubstr("b.dcm has a different one from 2 of the 4 slices "
                        "(e.g. a.dcm), 3 different values in all"));
  // Without strict: one stack, with the counts.
  const auto stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_TRUE(stack->frames_of_reference_differ);
  EXPECT_EQ(stack->frame_of_reference_uids, 3);
  EXPECT_EQ(stack->slices_without_frame_of_reference, 0);
  EXPECT_EQ(stack->order.size(), 4u);
}

TEST(LayOutDicomStackTest, OneFrameOfReferenceIsNotReportedAsDiffering) {
  std::vector<FileHeader> headers = {Slice("a.dcm", {0, 0, 0}),
                                     Slice("b.dcm", {0, 0, 1})};
  auto stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_FALSE(stack->frames_of_reference_differ);
  EXPECT_EQ(stack->frame_of_reference_uids, 1);
  for (FileHeader& h : headers) h.frame_of_reference_uid.clear();
  stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_FALSE(stack->frames_of_reference_differ);
  EXPECT_EQ(stack->slices_without_frame_of_reference, 2);
  // Some with one, some without: they differ.
  headers[0].frame_of_reference_uid = "1.2.3.4.5";
  stack = LayOut(headers);
  ASSERT_TRUE(stack.ok()) << stack.status();
  EXPECT_TRUE(stack->frames_of_reference_differ);
}

// Differing UIDs are let through only for a geometry that is one stack; when
// it is not, its error says that the UIDs differ too.
TEST(LayOutDicomStackTest, DifferingFramesOfReferenceNeedOneStack) {
  std::vector<FileHeader> headers = {Slice("a.dcm", {0, 0, 0}),
                                     Slice("b.dcm", {0, 0, 1}),
                                     Slice("c.dcm", {0, 0, 1})};
  headers[1].frame_of_reference_uid = "9.8.7.6";
  headers[2].frame_of_reference_uid = "9.8.7.7";
  const auto stack = LayOut(headers);
  EXPECT_EQ(stack.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(stack.status().message(),
              AllOf(HasSubstr("b.dcm and c.dcm are at the same slice position"),
                    HasSubstr("the slices' FrameOfReferenceUIDs differ as well "
                              "(3 different UIDs), which is accepted only when "
                              "the geometry is one stack"),
                    Not(HasSubstr("9.8.7"))));
  // One UID: the same error as ever.
  for (FileHeader& h : headers) h.frame_of_reference_uid = "1.2.3.4.5";
  EXPECT_THAT(LayOut(headers).status().message(),
              Not(HasSubstr("FrameOfReferenceUID")));
}

TEST(LayOutDicomStackTest, OddModalityAndPixelRepresentationShowTheValues) {
  std::vector<FileHeader> headers = {Slice("a.dcm", {0, 0, 0}),
                                     Slice("b.dcm", {0, 0, 1}),
                                     Slice("c.dcm", {0, 0, 2})};
  headers[0].modality = "MR";
  EXPECT_THAT(LayOut(headers).status().message(),
              HasSubstr("inconsistent Modality: a.dcm has MR, but 2 of the 3 "
                        "slices (e.g. b.dcm) have CT"));
  headers[0].modality = "CT";
  headers[2].layout.is_signed = true;
  EXPECT_THAT(LayOut(headers).status().message(),
              HasSubstr("inconsistent PixelRepresentation: c.dcm has 1 "
                        "(signed), but 2 of the 3 slices (e.g. a.dcm) have 0 "
                        "(unsigned)"));
}

TEST(LayOutDicomStackTest, SizeOrientationAndSpacingMustMatchTheFirstSlice) {
  std::vector<FileHeader> headers = {Slice("a.dcm", {0, 0, 0}),
                                     Slice("b.dcm", {0, 0, 1})};
  headers[1].rows = 6;
  EXPECT_THAT(LayOut(headers).status().message(),
              HasSubstr("inconsistent Rows/Columns: b.dcm is 5 x 6 (columns x "
                        "rows) but a.dcm is 5 x 4"));
  headers[1].rows = 4;
  headers[1].orientation[4] = 1 - 2e-4;
  EXPECT_THAT(LayOut(headers).status().message(),
              HasSubstr("inconsistent ImageOrientationPatient: b.dcm differs "
                        "from a.dcm"));
  headers[1].orientation[4] = 1 - 5e-5;  // within 1e-4
  EXPECT_TRUE(LayOut(headers).ok());
  headers[1].pixel_spacing[1] = 0.25 * (1 + 2e-4);
  EXPECT_THAT(LayOut(headers).status().message(),
              HasSubstr("inconsistent PixelSpacing: b.dcm has"));
}

TEST(LayOutDicomStackTest, NearlyOrthonormalOrientationIsOrthonormalised) {
  // Six-digit decimal strings: slightly off unit length and orthogonality.
  const std::array<double, 6> rounded = {0.999999,  0.000999, 0,
                                         -0.000999, 1.000001, 0.0005};
  const auto stack = LayOut(
      {Slice("a", {0, 0, 0}, rounded), Slice("b", {0, 0.0005, 1}, rounded)});
  ASSERT_TRUE(stack.ok()) << stack.status();
  const std::array<double, 9>& d = stack->grid.direction;
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) {
      double dot = 0;
      for (int r = 0; r < 3; ++r) dot += d[3 * r + a] * d[3 * r + b];
      EXPECT_NEAR(dot, a == b ? 1 : 0, 1e-12) << a << " " << b;
    }
  }

  const std::array<double, 6> skewed = {1, 0, 0, 0.01, 1, 0};
  const auto refused = LayOut({Slice("s.dcm", {0, 0, 0}, skewed)});
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(refused.status().message(),
              HasSubstr("s.dcm: ImageOrientationPatient is not two "
                        "orthogonal unit vectors"));
}

// A volume of `slices` slices of 4 x 3 voxels, value 100 * k + 10 * j + i.
Volume<float> Ramp(int slices) {
  Volume<float> v;
  v.grid.size = {4, 3, slices};
  v.data.resize(v.grid.VoxelCount());
  for (int k = 0; k < slices; ++k) {
    for (int j = 0; j < 3; ++j) {
      for (int i = 0; i < 4; ++i) {
        v.data[(k * 3 + j) * 4 + i] = 100.0f * k + 10.0f * j + i + 1;
      }
    }
  }
  return v;
}

DicomStackLayout Shifts(std::vector<std::array<double, 2>> shifts) {
  DicomStackLayout layout;
  layout.tilt_shift = std::move(shifts);
  return layout;
}

float At(const Volume<float>& v, int i, int j, int k) {
  return v.data[(k * v.grid.size[1] + j) * v.grid.size[0] + i];
}

TEST(CorrectGantryTiltTest, WholePixelShiftsMoveTheSliceAndPadWithTheMinimum) {
  Volume<float> v = Ramp(3);
  const Volume<float> original = v;
  // Slice 1 moved by one column, slice 2 by one row.
  ASSERT_TRUE(
      CorrectGantryTilt(Shifts({{0, 0}, {1, 0}, {0, 1}}), v, ComputeContext{})
          .ok());
  const float minimum = 1;  // voxel (0, 0, 0)
  for (int j = 0; j < 3; ++j) {
    for (int i = 0; i < 4; ++i) {
      EXPECT_EQ(At(v, i, j, 0), At(original, i, j, 0));
      EXPECT_EQ(At(v, i, j, 1), i == 0 ? minimum : At(original, i - 1, j, 1))
          << i << " " << j;
      EXPECT_EQ(At(v, i, j, 2), j == 0 ? minimum : At(original, i, j - 1, 2))
          << i << " " << j;
    }
  }
}

TEST(CorrectGantryTiltTest, HalfPixelShiftsInterpolateBilinearly) {
  Volume<float> v = Ramp(2);
  const Volume<float> original = v;
  ASSERT_TRUE(
      CorrectGantryTilt(Shifts({{0, 0}, {0.5, 0.5}}), v, ComputeContext{})
          .ok());
  // Voxel (i, j) of slice 1 samples (i - 0.5, j - 0.5): the mean of four.
  for (int j = 1; j < 3; ++j) {
    for (int i = 1; i < 4; ++i) {
      const float mean =
          (At(original, i - 1, j - 1, 1) + At(original, i, j - 1, 1) +
           At(original, i - 1, j, 1) + At(original, i, j, 1)) /
          4;
      EXPECT_FLOAT_EQ(At(v, i, j, 1), mean) << i << " " << j;
    }
  }
}

TEST(CorrectGantryTiltTest, ResultDoesNotDependOnTheThreadCount) {
  std::mt19937 random(7);
  std::uniform_real_distribution<float> value(-1000, 1000);
  std::uniform_real_distribution<double> shift(-2.5, 2.5);
  Volume<float> one = Ramp(16);
  for (float& x : one.data) x = value(random);
  std::vector<std::array<double, 2>> shifts(16);
  for (auto& s : shifts) s = {shift(random), shift(random)};
  Volume<float> two = one;
  ComputeContext single;
  single.threads = 1;
  ComputeContext dual;
  dual.threads = 2;
  ASSERT_TRUE(CorrectGantryTilt(Shifts(shifts), one, single).ok());
  ASSERT_TRUE(CorrectGantryTilt(Shifts(shifts), two, dual).ok());
  EXPECT_EQ(one.data, two.data);
  EXPECT_NE(one.data, Ramp(16).data);
}

TEST(CorrectGantryTiltTest, AnUntiltedLayoutLeavesTheImage) {
  Volume<float> v = Ramp(2);
  ASSERT_TRUE(CorrectGantryTilt(DicomStackLayout{}, v, ComputeContext{}).ok());
  EXPECT_EQ(v.data, Ramp(2).data);
}

TEST(CorrectGantryTiltTest, AnImageOfAnotherSizeIsRefusedUntouched) {
  Volume<float> v = Ramp(2);
  const auto status =
      CorrectGantryTilt(Shifts({{0, 0}, {1, 0}, {2, 0}}), v, ComputeContext{});
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(v.data, Ramp(2).data);
}

}  // namespace
}  // namespace interslice
