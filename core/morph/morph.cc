#include "core/morph/morph.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <exception>
#include <mutex>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "core/common/status_macros.h"
#include "core/morph/morph_internal.h"
#include "itkConnectedComponentImageFilter.h"
#include "itkFastSymmetricForcesDemonsRegistrationFilter.h"
#include "itkGaussianOperator.h"
#include "itkImage.h"
#include "itkMultiResolutionPDEDeformableRegistration.h"
#include "itkVector.h"
#include "tbb/parallel_for.h"
#include "tbb/task_arena.h"

namespace interslice {
namespace {

using morph_internal::MonotoneTangent;
using morph_internal::Sample;

using Image = itk::Image<float, 2>;
using Displacement = itk::Vector<float, 2>;
using Field = itk::Image<Displacement, 2>;

Image::Pointer MakeImage(const std::vector<float>& data, int64_t nx,
                         int64_t ny) {
  Image::Pointer image = Image::New();
  Image::RegionType region;
  region.SetSize({static_cast<itk::SizeValueType>(nx),
                  static_cast<itk::SizeValueType>(ny)});
  image->SetRegions(region);
  image->Allocate();
  std::copy(data.begin(), data.end(), image->GetBufferPointer());
  return image;
}

// ITK's symmetric-forces demons with its per-iteration helper filters on the
// filter's own work units. ITK 5.2 runs the displacement smoothing (the
// regulariser, PDEDeformableRegistrationFilter::SmoothDisplacementField) and
// the field update (ApplyUpdate's adder) in filters it creates itself, which
// take ITK's process-wide default number of threads: every demons iteration
// then hands three small jobs to ITK's global thread pool and waits for them,
// whatever SetNumberOfWorkUnits says, and whatever the ComputeContext gives
// (profiled on the phantom fill of issue 24: the pool's wake-ups and waits
// were ~12% of the CPU and most of the per-iteration cost). This subclass
// computes the same two steps with the same ITK operator on the calling
// thread (RegisterSlicesCoarse runs the filter with 1 work unit; the
// caller's tbb arena bounds the parallelism). The results are
// identical: the same Gaussian operator (variance sigma^2, the filter's
// maximum error and kernel width) applied along x then y with the same
// boundary condition, and the same float sum for the update (the demons
// function's time step is 1; another time step scales the update first, as
// ITK does). Only ESMDemonsRegistrationFunction's warper, private to ITK,
// still takes the global default.
class DemonsOnOwnWorkUnits
    : public itk::FastSymmetricForcesDemonsRegistrationFilter<Image, Image,
                                                              Field> {
 public:
  ITK_DISALLOW_COPY_AND_MOVE(DemonsOnOwnWorkUnits);
  using Self = DemonsOnOwnWorkUnits;
  using Superclass =
      itk::FastSymmetricForcesDemonsRegistrationFilter<Image, Image, Field>;
  using Pointer = itk::SmartPointer<Self>;
  using ConstPointer = itk::SmartPointer<const Self>;
  itkNewMacro(Self);
  itkTypeMacro(DemonsOnOwnWorkUnits,
               FastSymmetricForcesDemonsRegistrationFilter);

 protected:
  DemonsOnOwnWorkUnits() = default;
  ~DemonsOnOwnWorkUnits() override = default;

  void ApplyUpdate(const TimeStepType& dt) override {
    // ITK's own (on the global pool); RegisterSlicesCoarse never sets it.
    if (this->GetSmoothUpdateField()) this->SmoothUpdateField();
    Field* field = this->GetOutput();
    Field* update = this->GetUpdateBuffer();
    const itk::SizeValueType count =
        field->GetBufferedRegion().GetNumberOfPixels();
    if (update->GetBufferedRegion() != field->GetBufferedRegion()) {
      itkExceptionMacro(<< "update and displacement regions differ");
    }
    Displacement* f = field->GetBufferPointer();
    Displacement* u = update->GetBufferPointer();
    if (std::fabs(dt - 1.0) > 1.0e-4) {
      for (itk::SizeValueType v = 0; v < count; ++v) u[v] = u[v] * dt;
    }
    for (itk::SizeValueType v = 0; v < count; ++v) f[v] = f[v] + u[v];
    const auto* function = dynamic_cast<
        const itk::ESMDemonsRegistrationFunction<Image, Image, Field>*>(
        this->GetDifferenceFunction().GetPointer());
    if (function == nullptr) {
      itkExceptionMacro(<< "unexpected demons difference function");
    }
    this->SetRMSChange(function->GetRMSChange());
    if (this->GetSmoothDisplacementField()) this->SmoothDisplacementField();
    // The buffer changed in place: without a new time stamp the demons
    // function's warper would not warp the moving image by the new field
    // in the next iteration (ITK's own ApplyUpdate grafts a new output).
    field->Modified();
  }

  // The regulariser: the field convolved along x, then along y, with ITK's
  // GaussianOperator (variance sigma^2, the filter's maximum error and kernel
  // width), the coefficients taken from the operator itself. The loop is
  // VectorNeighborhoodOperatorImageFilter's, written for the one case used
  // here: per pixel and component a float sum over the kernel in its order
  // (offset -r .. r), float products, the image edge extended
  // (ZeroFluxNeumannBoundaryCondition: an offset beyond the border reads the
  // border pixel). So the result is bit for bit ITK's (tested against the
  // stock filter), at a fraction of the cost: ITK's generic neighbourhood
  // iterator with bounds checks per pixel was ~20% of auto's CPU (issue 24).
  void SmoothDisplacementField() override {
    Field* field = this->GetOutput();
    const auto size = field->GetBufferedRegion().GetSize();
    const int64_t nx = static_cast<int64_t>(size[0]);
    const int64_t ny = static_cast<int64_t>(size[1]);
    Displacement* f = field->GetBufferPointer();
    scratch_.resize(static_cast<size_t>(nx * ny));
    for (unsigned axis = 0; axis < 2; ++axis) {
      itk::GaussianOperator<float, 2> gaussian;
      gaussian.SetDirection(axis);
      const double sigma = this->GetStandardDeviations()[axis];
      gaussian.SetVariance(sigma * sigma);
      gaussian.SetMaximumError(this->GetMaximumError());
      gaussian.SetMaximumKernelWidth(this->GetMaximumKernelWidth());
      gaussian.CreateDirectional();
      // A directional operator: 2r + 1 coefficients along `axis`, in the
      // order of the offsets -r .. r.
      const int64_t r = static_cast<int64_t>(gaussian.GetRadius(axis));
      const std::vector<float> w(gaussian.Begin(), gaussian.End());
      if (static_cast<int64_t>(w.size()) != 2 * r + 1) {
        itkExceptionMacro(<< "unexpected Gaussian operator size");
      }
      // x: field -> scratch; y: scratch -> field.
      const Displacement* src = axis == 0 ? f : scratch_.data();
      Displacement* dst = axis == 0 ? scratch_.data() : f;
      const int64_t n_along = axis == 0 ? nx : ny;
      const int64_t step = axis == 0 ? 1 : nx;
      for (int64_t j = 0; j < ny; ++j) {
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t along = axis == 0 ? i : j;
          const Displacement* line = src + (i + nx * j) - along * step;
          float sum0 = 0.0f, sum1 = 0.0f;
          for (int64_t k = 0; k <= 2 * r; ++k) {
            const int64_t at =
                std::clamp<int64_t>(along + k - r, 0, n_along - 1);
            const Displacement& p = line[at * step];
            sum0 += w[k] * p[0];
            sum1 += w[k] * p[1];
          }
          dst[i + nx * j][0] = sum0;
          dst[i + nx * j][1] = sum1;
        }
      }
    }
  }

 private:
  std::vector<Displacement> scratch_;
};

// Block mean by `d` (partial blocks at the border averaged over what exists),
// after clipping to +-clip.
std::vector<float> ClipAndShrink(const float* in, int64_t nx, int64_t ny, int d,
                                 float clip, int64_t& mx, int64_t& my) {
  mx = (nx + d - 1) / d;
  my = (ny + d - 1) / d;
  std::vector<float> out(mx * my, 0.0f);
  std::vector<int> count(mx * my, 0);
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < nx; ++i) {
      const int64_t c = (i / d) + mx * (j / d);
      out[c] += std::clamp(in[i + nx * j], -clip, clip);
      ++count[c];
    }
  for (int64_t c = 0; c < mx * my; ++c) out[c] /= static_cast<float>(count[c]);
  return out;
}

absl::Status ValidateOptions(const MorphOptions& o) {
  if (o.levels < 1 || o.levels > 8)
    return absl::InvalidArgumentError("morph: levels must be in [1, 8]");
  if (o.iterations < 0)
    return absl::InvalidArgumentError("morph: iterations must be >= 0");
  if (!(o.field_sigma_px > 0) || !std::isfinite(o.field_sigma_px))
    return absl::InvalidArgumentError("morph: field_sigma_px must be > 0");
  if (!(o.clip_mm > 0) || !std::isfinite(o.clip_mm))
    return absl::InvalidArgumentError("morph: clip_mm must be > 0");
  if (o.downsample < 1 || o.downsample > 16)
    return absl::InvalidArgumentError("morph: downsample must be in [1, 16]");
  if (o.trajectory != MorphTrajectory::kPiecewiseLinear &&
      o.trajectory != MorphTrajectory::kCubic)
    return absl::InvalidArgumentError("morph: unknown trajectory");
  if (o.values != MorphValues::kLinear &&
      o.values != MorphValues::kCatmullRom &&
      o.values != MorphValues::kSmoothstep &&
      o.values != MorphValues::kMonotone)
    return absl::InvalidArgumentError("morph: unknown value interpolation");
  return absl::OkStatus();
}

}  // namespace

absl::Status ValidateMorphOptions(const MorphOptions& options) {
  return ValidateOptions(options);
}

void CoarseDisplacement::Sample(double x, double y, float& out_x,
                                float& out_y) const {
  // Coarse pixel c's centre is at fine coordinate c d + (d - 1) / 2.
  const double half = (downsample - 1) / 2.0;
  const double cx = (x - half) / downsample, cy = (y - half) / downsample;
  out_x = downsample * morph_internal::Sample(ux.data(), mx, my, cx, cy);
  out_y = downsample * morph_internal::Sample(uy.data(), mx, my, cx, cy);
}

std::vector<float> CoarseDisplacement::Upsample() const {
  std::vector<float> u(2 * nx * ny, 0.0f);
  for (int64_t j = 0; j < ny; ++j)
    for (int64_t i = 0; i < nx; ++i)
      Sample(static_cast<double>(i), static_cast<double>(j), u[i + nx * j],
             u[nx * ny + i + nx * j]);
  return u;
}

absl::StatusOr<CoarseDisplacement> RegisterSlicesCoarse(
    const float* fixed, const float* moving, int64_t nx, int64_t ny,
    const MorphOptions& options) {
  INTERSLICE_RETURN_IF_ERROR(ValidateOptions(options));
  if (nx < 1 || ny < 1) return absl::InvalidArgumentError("morph: empty slice");
  CoarseDisplacement out;
  out.nx = nx;
  out.ny = ny;
  const int d = options.downsample;
  out.downsample = d;
  out.mx = (nx + d - 1) / d;
  out.my = (ny + d - 1) / d;
  out.ux.assign(out.mx * out.my, 0.0f);
  out.uy.assign(out.mx * out.my, 0.0f);
  if (options.iterations == 0) return out;
  int64_t mx = 0, my = 0;
  const float clip = static_cast<float>(options.clip_mm);
  const std::vector<float> f = ClipAndShrink(fixed, nx, ny, d, clip, mx, my);
  const std::vector<float> m = ClipAndShrink(moving, nx, ny, d, clip, mx, my);
  // Every level must keep at least 4 pixels per side.
  int levels = options.levels;
  while (levels > 1 && (std::min(mx, my) >> (levels - 1)) < 4) --levels;

  using Demons = DemonsOnOwnWorkUnits;
  using MultiResolution =
      itk::MultiResolutionPDEDeformableRegistration<Image, Image, Field, float>;
  Field::Pointer field;
  try {
    auto demons = Demons::New();
    demons->SetStandardDeviations(options.field_sigma_px);
    demons->SetSmoothDisplacementField(true);
    demons->SetNumberOfWorkUnits(1);
    auto multi = MultiResolution::New();
    multi->SetRegistrationFilter(demons);
    multi->SetNumberOfLevels(static_cast<unsigned>(levels));
    MultiResolution::NumberOfIterationsType its(levels);
    its.Fill(static_cast<unsigned>(options.iterations));
    multi->SetNumberOfIterations(its);
    multi->GetModifiableFixedImagePyramid()->SetNumberOfWorkUnits(1);
    multi->GetModifiableMovingImagePyramid()->SetNumberOfWorkUnits(1);
    multi->GetModifiableFieldExpander()->SetNumberOfWorkUnits(1);
    multi->SetNumberOfWorkUnits(1);
    multi->SetFixedImage(MakeImage(f, mx, my));
    multi->SetMovingImage(MakeImage(m, mx, my));
    multi->Update();
    field = multi->GetOutput();
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("morph: ITK registration: ", e.what()));
  }
  const Displacement* buffer = field->GetBufferPointer();
  for (int64_t c = 0; c < mx * my; ++c) {
    out.ux[c] = buffer[c][0];
    out.uy[c] = buffer[c][1];
  }
  return out;
}

absl::StatusOr<std::vector<float>> RegisterSlices(const float* fixed,
                                                  const float* moving,
                                                  int64_t nx, int64_t ny,
                                                  const MorphOptions& options) {
  INTERSLICE_ASSIGN_OR_RETURN(
      const CoarseDisplacement coarse,
      RegisterSlicesCoarse(fixed, moving, nx, ny, options));
  // Upsample: coarse pixel c covers fine pixels [c d, c d + d); its centre is
  // at fine coordinate c d + (d - 1) / 2. Displacements scale by d.
  return coarse.Upsample();
}

absl::StatusOr<MorphedField> StackMorph(const Volume<float>& slice_maps,
                                        const StackPlan& plan,
                                        const MorphOptions& options,
                                        int64_t max_voxels,
                                        const ComputeContext& context) {
  INTERSLICE_RETURN_IF_ERROR(ValidateOptions(options));
  const bool cubic = options.trajectory == MorphTrajectory::kCubic;
  // The linear stacking fixes the grid, the fixed slices and the checks.
  MorphedField out;
  INTERSLICE_ASSIGN_OR_RETURN(
      out.stacked, StackLinear(slice_maps, plan, max_voxels, context));
  const Grid& g = slice_maps.grid;
  const int64_t nx = g.size[0], ny = g.size[1], plane = nx * ny;
  const int64_t gaps = g.size[2] - 1;
  out.statistics.gaps = static_cast<int>(std::max<int64_t>(0, gaps));
  // With u = 0 the piecewise morph is the linear stacking; the cubic one
  // still interpolates the values by options.values, so it goes on.
  if (gaps < 1 || (options.iterations == 0 && !cubic)) return out;

  std::vector<double> sum(gaps, 0.0), worst(gaps, 0.0);
  // kCubic keeps every gap's field: a gap's slices need its neighbours'.
  std::vector<std::vector<float>> fields(cubic ? gaps : 0);
  std::atomic<bool> cancelled{false};
  absl::Status failure;
  std::mutex failure_mutex;
  // The gaps run in parallel, but ComputeContext::Report must never be
  // called concurrently (core/common/compute.h: a worker process writes each
  // report as a frame of its protocol, and two at once corrupt it): one lock.
  std::mutex report_mutex;
  auto report = [&](double fraction) {
    std::lock_guard<std::mutex> lock(report_mutex);
    context.Report({.stage = "stack", .fraction = fraction});
  };
  const double sx = g.spacing[0], sy = g.spacing[1];
  float* dst = out.stacked.field.data.data();
  const float* maps = slice_maps.data.data();
  auto poll = [&]() {
    if (cancelled.load()) return false;
    if (!context.CheckCancelled().ok()) {
      cancelled.store(true);
      return false;
    }
    return true;
  };
  // Phase 1: register every gap (and, piecewise, write its slices at once:
  // nothing else needs its field).
  auto register_gap = [&](int64_t s) {
    if (!poll()) return;
    const float* d0 = maps + s * plane;
    const float* d1 = maps + (s + 1) * plane;
    absl::StatusOr<std::vector<float>> u =
        RegisterSlices(d0, d1, nx, ny, options);
    if (!u.ok()) {
      std::lock_guard<std::mutex> lock(failure_mutex);
      if (failure.ok()) failure = u.status();
      return;
    }
    const float* ux = u->data();
    const float* uy = u->data() + plane;
    double total = 0, largest = 0;
    for (int64_t v = 0; v < plane; ++v) {
      const double len = std::hypot(ux[v] * sx, uy[v] * sy);
      total += len;
      largest = std::max(largest, len);
    }
    sum[s] = total / static_cast<double>(plane);
    worst[s] = largest;
    if (cubic) {
      fields[s] = *std::move(u);
      return;
    }
    const int64_t k0 = plan.nodes[s], k1 = plan.nodes[s + 1];
    for (int64_t k = k0 + 1; k < k1; ++k) {
      const double t =
          static_cast<double>(k - k0) / static_cast<double>(k1 - k0);
      float* slice = dst + k * plane;
      for (int64_t j = 0; j < ny; ++j)
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t v = i + nx * j;
          const double a = Sample(d0, nx, ny, i - t * ux[v], j - t * uy[v]);
          const double b =
              Sample(d1, nx, ny, i + (1 - t) * ux[v], j + (1 - t) * uy[v]);
          slice[v] = static_cast<float>((1 - t) * a + t * b);
        }
    }
  };
  // Phase 2 (kCubic): the slices of gap s from the fields of gaps s-1, s,
  // s+1 and the maps of key slices s-1 .. s+2 (see morph.h for the
  // formulas). Cubic Hermite interpolation with Catmull-Rom tangents
  // (Catmull & Rom 1974): the tangent at a key slice is the chord slope over
  // its two gaps, the same from both sides, which makes the trajectory and
  // the value C1 there. t and the tangents are in units of this gap; for
  // uneven gaps the per-output-slice chord slope is scaled by its length.
  auto write_cubic_gap = [&](int64_t s) {
    if (!poll()) return;
    const bool has_prev = s > 0, has_next = s + 1 < gaps;
    const double len = static_cast<double>(plan.nodes[s + 1] - plan.nodes[s]);
    const double len_prev =
        has_prev ? static_cast<double>(plan.nodes[s] - plan.nodes[s - 1]) : 0;
    const double len_next =
        has_next ? static_cast<double>(plan.nodes[s + 2] - plan.nodes[s + 1])
                 : 0;
    // Scale of the chord slopes into this gap's units.
    const double w_prev = has_prev ? len / (len_prev + len) : 0;
    const double w_next = has_next ? len / (len + len_next) : 0;
    const float* d0 = maps + s * plane;
    const float* d1 = maps + (s + 1) * plane;
    const float* dm = has_prev ? maps + (s - 1) * plane : nullptr;
    const float* dp = has_next ? maps + (s + 2) * plane : nullptr;
    const float* ux = fields[s].data();
    const float* uy = ux + plane;
    const float* px = has_prev ? fields[s - 1].data() : nullptr;
    const float* py = has_prev ? px + plane : nullptr;
    const float* qx = has_next ? fields[s + 1].data() : nullptr;
    const float* qy = has_next ? qx + plane : nullptr;
    const int64_t k0 = plan.nodes[s], k1 = plan.nodes[s + 1];
    for (int64_t k = k0 + 1; k < k1; ++k) {
      const double t =
          static_cast<double>(k - k0) / static_cast<double>(k1 - k0);
      const double t2 = t * t, t3 = t2 * t;
      const double h00 = 2 * t3 - 3 * t2 + 1, h10 = t3 - 2 * t2 + t;
      const double h01 = 3 * t2 - 2 * t3, h11 = t3 - t2;
      float* slice = dst + k * plane;
      for (int64_t j = 0; j < ny; ++j)
        for (int64_t i = 0; i < nx; ++i) {
          const int64_t v = i + nx * j;
          const double u_x = ux[v], u_y = uy[v];
          // Trajectory tangents at key slices s and s+1 (one-sided: u).
          const double vs_x = has_prev ? w_prev * (px[v] + u_x) : u_x;
          const double vs_y = has_prev ? w_prev * (py[v] + u_y) : u_y;
          const double ve_x = has_next ? w_next * (u_x + qx[v]) : u_x;
          const double ve_y = has_next ? w_next * (u_y + qy[v]) : u_y;
          // h(t): displacement from key slice s along the trajectory.
          const double h_x = h10 * vs_x + h01 * u_x + h11 * ve_x;
          const double h_y = h10 * vs_y + h01 * u_y + h11 * ve_y;
          const double x0 = i - h_x, y0 = j - h_y;    // on key slice s
          const double x1 = x0 + u_x, y1 = y0 + u_y;  // on key slice s+1
          const double a0 = Sample(d0, nx, ny, x0, y0);
          const double a1 = Sample(d1, nx, ny, x1, y1);
          if (options.values == MorphValues::kLinear) {
            slice[v] = static_cast<float>((1 - t) * a0 + t * a1);
            continue;
          }
          if (options.values == MorphValues::kSmoothstep) {
            // Zero value tangents: h00 + h01 = 1, a convex blend.
            slice[v] = static_cast<float>(h00 * a0 + h01 * a1);
            continue;
          }
          // Value tangents from key slices s-1 and s+2, reached along the
          // trajectory through the neighbouring gaps' fields: Catmull-Rom's
          // chord slopes, or the monotone (PCHIP) limited slopes.
          double m0 = a1 - a0, m1 = a1 - a0;
          if (options.values == MorphValues::kMonotone) {
            const double slope = (a1 - a0) / len;  // per output slice
            if (has_prev) {
              const double am = Sample(dm, nx, ny, x0 - px[v], y0 - py[v]);
              m0 = len *
                   MonotoneTangent((a0 - am) / len_prev, slope, len_prev, len);
            }
            if (has_next) {
              const double ap = Sample(dp, nx, ny, x1 + qx[v], y1 + qy[v]);
              m1 = len *
                   MonotoneTangent(slope, (ap - a1) / len_next, len, len_next);
            }
          } else {
            if (has_prev)
              m0 = w_prev * (a1 - Sample(dm, nx, ny, x0 - px[v], y0 - py[v]));
            if (has_next)
              m1 = w_next * (Sample(dp, nx, ny, x1 + qx[v], y1 + qy[v]) - a0);
          }
          slice[v] =
              static_cast<float>(h00 * a0 + h10 * m0 + h01 * a1 + h11 * m1);
        }
    }
  };
  tbb::task_arena arena(context.threads > 0 ? context.threads
                                            : tbb::task_arena::automatic);
  arena.execute([&] {
    tbb::parallel_for(int64_t{0}, gaps, [&](int64_t s) {
      register_gap(s);
      report(0.0);
    });
  });
  if (cancelled.load()) return context.CheckCancelled();
  if (!failure.ok()) return failure;
  if (cubic) {
    arena.execute([&] {
      tbb::parallel_for(int64_t{0}, gaps,
                        [&](int64_t s) { write_cubic_gap(s); });
    });
    if (cancelled.load()) return context.CheckCancelled();
  }
  double total = 0;
  for (int64_t s = 0; s < gaps; ++s) {
    total += sum[s];
    out.statistics.max_displacement_mm =
        std::max(out.statistics.max_displacement_mm, worst[s]);
  }
  out.statistics.mean_displacement_mm = total / static_cast<double>(gaps);
  return out;
}

absl::StatusOr<int64_t> RemoveUnsupportedComponents(
    Volume<float>& field, const std::vector<uint8_t>& fixed_slices,
    float margin_mm, const ComputeContext& context) {
  const Index3 n = field.grid.size;
  if (static_cast<int64_t>(fixed_slices.size()) != n[2] ||
      static_cast<int64_t>(field.data.size()) != field.grid.VoxelCount())
    return absl::InvalidArgumentError(
        "component filter: field and fixed slices do not match");
  if (!(margin_mm > 0))
    return absl::InvalidArgumentError("component filter: margin must be > 0");
  INTERSLICE_RETURN_IF_ERROR(context.CheckCancelled());
  using Mask = itk::Image<uint8_t, 3>;
  using Labels = itk::Image<uint32_t, 3>;
  Mask::Pointer mask = Mask::New();
  Mask::RegionType region;
  region.SetSize({static_cast<itk::SizeValueType>(n[0]),
                  static_cast<itk::SizeValueType>(n[1]),
                  static_cast<itk::SizeValueType>(n[2])});
  mask->SetRegions(region);
  mask->Allocate();
  uint8_t* m = mask->GetBufferPointer();
  const int64_t count = field.grid.VoxelCount();
  for (int64_t v = 0; v < count; ++v) m[v] = field.data[v] >= 0 ? 1 : 0;
  Labels::Pointer labels;
  try {
    auto cc = itk::ConnectedComponentImageFilter<Mask, Labels>::New();
    cc->SetInput(mask);
    cc->SetFullyConnected(false);  // face connectivity
    if (context.threads > 0) cc->SetNumberOfWorkUnits(context.threads);
    cc->Update();
    labels = cc->GetOutput();
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("component filter: ITK: ", e.what()));
  }
  const uint32_t* l = labels->GetBufferPointer();
  uint32_t max_label = 0;
  for (int64_t v = 0; v < count; ++v) max_label = std::max(max_label, l[v]);
  std::vector<uint8_t> supported(static_cast<size_t>(max_label) + 1, 0);
  const int64_t plane = n[0] * n[1];
  for (int64_t k = 0; k < n[2]; ++k) {
    if (!fixed_slices[k]) continue;
    for (int64_t v = k * plane; v < (k + 1) * plane; ++v) supported[l[v]] = 1;
  }
  std::vector<uint8_t> removed(supported.size(), 0);
  int64_t removed_count = 0;
  for (int64_t v = 0; v < count; ++v) {
    const uint32_t label = l[v];
    if (label == 0 || supported[label]) continue;
    field.data[v] = std::min(field.data[v], -margin_mm);
    if (!removed[label]) {
      removed[label] = 1;
      ++removed_count;
    }
  }
  return removed_count;
}

}  // namespace interslice
