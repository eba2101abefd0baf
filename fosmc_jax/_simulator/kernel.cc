// The fast path's time loop as one XLA FFI kernel for the CPU (fosmc_jax/_simulator/native.py builds it
// with the host's C++ compiler and registers it).
//
// It advances L steps of the ideal-loop FOSMC ((14), (23) or the equivalent law, switching
// (28), sign, sat or tanh) on linear plants (3), exactly the operations of
// fosmc_jax._simulator.linear_path._linear_batch's ``body`` in the same order, for N independent rollouts
// ("lanes"). Everything that depends on time only (X_d at the integrator's stage times, and at
// the sample: X_d, Omega (10), the reference part of rho) comes in a table computed by JAX, so
// any reference works. The rollouts are held W at a time in SIMD lanes with the time loop
// inside (the structure of ../shared/anchors/simd_kernel), and blocks of W are spread over
// XLA's intra-op thread pool.
//
// Layouts (T = float or double; rows of N lanes, lane-minor):
//   ab      (36, N)  rows 0-26: the plant's A rows (3 x 9), 27-35: its B rows (3 x 3)
//   consts  (100,)   C (27), S = C(A + BK) (27), (CB)^-1 (9), K (27), gamma (3), delta (3),
//                    dt, the low-pass's decay and weight over a step (chattering_hf), the
//                    divergence bound
//   table   (L, R)   per step: X_d at the stage times (9 each: t; or t, t + dt/2, t + dt for
//                    RK4), then at the sample t' = (k + 1) dt: X_d (9), Omega (3), rho_ref, t'
//   carry   (47, N)  x (9), w (3), U (3), the accumulator's 10 fields x 3 joints (field-major,
//                    as fosmc_jax._simulator.metrics.Accumulator), diverged (0 / 1), diverged_at
#include <limits>

#include "kernel.h"
#include "layout.h"  // generated from the Python side (fosmc_jax._simulator.native.layout_header)

namespace ffi = xla::ffi;

namespace {

using fosmc::Simd;
using namespace fosmc::acc;  // the accumulator's fields
using fosmc::linear::kAcc, fosmc::linear::kDiv, fosmc::linear::kDivAt, fosmc::linear::kRows;
enum { kX = 0, kWi = 9, kU = 12 };  // x, w, U: the rows before the accumulator
static_assert(kAcc == kU + 3, "layout.h: the accumulator follows x, w and U");
static_assert(kFields == 10, "layout.h: the accumulator's fields changed; update Block's update of them");

template <typename T>
struct Consts {
  T C[27], S[27], CBi[9], K[27], gamma[3], delta[3], dt, decay, hf_weight, bound;
};

template <typename T, int Rk4>
void Block(const Consts<T>& c, int sw_code, int law_code, const T* ab, const T* table, int64_t L, int64_t R, const T* in, T* out, int64_t N) {
  using S = Simd<T>;
  using V = typename S::V;
  V st[kRows], A[27], B[9];
  for (int r = 0; r < kRows; r++) st[r] = S::Load(in + r * N);
  for (int q = 0; q < 27; q++) A[q] = S::Load(ab + q * N);
  for (int q = 0; q < 9; q++) B[q] = S::Load(ab + (27 + q) * N);
  const T dt = c.dt, half = c.dt / 2, big = std::numeric_limits<T>::max();
  V zero = {};
  // dx/dt and dw/dt (the field of _linear_batch): x' = (x2, x3, jerk_1, ...), w' = S (x - X_d)
  auto field = [&](const V* U, const V* x, const T* xd, V* dx, V* dw) {
    for (int j = 0; j < 3; j++) {
      V ax = A[9 * j] * x[0];
      for (int i = 1; i < 9; i++) ax += A[9 * j + i] * x[i];
      V bu = B[3 * j] * U[0] + B[3 * j + 1] * U[1];
      bu += B[3 * j + 2] * U[2];
      dx[3 * j] = x[3 * j + 1];
      dx[3 * j + 1] = x[3 * j + 2];
      dx[3 * j + 2] = ax + bu;
    }
    V z[9];
    for (int i = 0; i < 9; i++) z[i] = x[i] - xd[i];
    for (int j = 0; j < 3; j++) {
      V q = c.S[9 * j] * z[0];
      for (int i = 1; i < 9; i++) q += c.S[9 * j + i] * z[i];
      dw[j] = q;
    }
  };
  for (int64_t k = 0; k < L; k++) {
    const T* row = table + k * R;
    const T* sample = row + (Rk4 ? 27 : 9);  // X_d (9), Omega (3), rho_ref, t'
    const V *x = st + kX, *w = st + kWi, *U = st + kU;
    // the integrator step, as fosmc_jax._simulator.step._euler / _rk4
    V nx[9], nw[3], k1x[9], k1w[3];
    field(U, x, row, k1x, k1w);
    if constexpr (!Rk4) {
      for (int i = 0; i < 9; i++) nx[i] = x[i] + dt * k1x[i];
      for (int j = 0; j < 3; j++) nw[j] = w[j] + dt * k1w[j];
    } else {
      V y[12], k2x[9], k2w[3], k3x[9], k3w[3], k4x[9], k4w[3];
      V* yw = y + 9;
      for (int i = 0; i < 9; i++) y[i] = x[i] + half * k1x[i];
      for (int j = 0; j < 3; j++) yw[j] = w[j] + half * k1w[j];
      field(U, y, row + 9, k2x, k2w);
      for (int i = 0; i < 9; i++) y[i] = x[i] + half * k2x[i];
      for (int j = 0; j < 3; j++) yw[j] = w[j] + half * k2w[j];
      field(U, y, row + 9, k3x, k3w);
      for (int i = 0; i < 9; i++) y[i] = x[i] + dt * k3x[i];
      for (int j = 0; j < 3; j++) yw[j] = w[j] + dt * k3w[j];
      field(U, y, row + 18, k4x, k4w);
      for (int i = 0; i < 9; i++) nx[i] = x[i] + dt * ((k1x[i] + 2 * k2x[i] + 2 * k3x[i] + k4x[i]) / 6);
      for (int j = 0; j < 3; j++) nw[j] = w[j] + dt * ((k1w[j] + 2 * k2w[j] + 2 * k3w[j] + k4w[j]) / 6);
    }
    // the controller sample at t' (_linear_batch's ``sample``)
    V Z[9];
    for (int i = 0; i < 9; i++) Z[i] = nx[i] - sample[i];
    V zz = Z[0] * Z[0];
    for (int i = 1; i < 9; i++) zz += Z[i] * Z[i];
    const V rho = c.gamma[0] * (zz > 0 ? S::Sqrt(zz) : zero) + sample[12];  // safe_sqrt
    V s[3], f[3], nU[3];
    for (int j = 0; j < 3; j++) {
      V cz = c.C[9 * j] * Z[0];
      for (int i = 1; i < 9; i++) cz += c.C[9 * j + i] * Z[i];
      s[j] = cz - nw[j];
      const T d = c.delta[j];
      V sw;  // the switching function f(s)
      // the codes are positions in fosmc_jax._controllers.fosmc.SWITCHING and LAWS (one per call: a
      // branch every lane takes alike, as in arm_kernel.cc; templates on them made 32 copies)
      if (sw_code == 0) sw = s[j] > 0 ? zero + 1 : (s[j] < 0 ? zero - 1 : s[j]);  // sign
      else if (sw_code == 1) sw = s[j] / (S::Abs(s[j]) + d);                       // ratio (28)
      else if (sw_code == 2) sw = S::Min(S::Max(s[j] / d, zero - 1), zero + 1);   // sat
      else sw = S::Map(s[j] / d, [](T a) { return std::tanh(a); });
      f[j] = rho * sw;
    }
    for (int j = 0; j < 3; j++) {
      V q = c.CBi[3 * j] * f[0] + c.CBi[3 * j + 1] * f[1];
      q += c.CBi[3 * j + 2] * f[2];
      nU[j] = sample[9 + j] - q;
      if (law_code == 1) {
        V kz = c.K[9 * j] * Z[0];
        for (int i = 1; i < 9; i++) kz += c.K[9 * j + i] * Z[i];
        nU[j] = nU[j] + kz;
      }
    }
    auto ok = S::Abs(nx[0]) <= c.bound;  // a lane mask; NaN fails every comparison
    for (int i = 1; i < 9; i++) ok &= S::Abs(nx[i]) <= c.bound;
    for (int j = 0; j < 3; j++) ok &= (S::Abs(nw[j]) <= big) & (S::Abs(nU[j]) <= big) & (S::Abs(s[j]) <= big);
    // _simulator._guard: a rollout that diverged, or fails now, keeps its old carry
    const auto diverged = st[kDiv] != 0;
    const auto keep = diverged | ~ok;
    st[kDivAt] = (~diverged & ~ok) ? zero + sample[13] : st[kDivAt];
    st[kDiv] = keep ? zero + 1 : zero;
    for (int i = 0; i < 9; i++) st[kX + i] = keep ? st[kX + i] : nx[i];
    for (int j = 0; j < 3; j++) {
      // fosmc_jax._simulator.metrics.add (no actuator limit: ``saturated`` stays)
      V* a = st + kAcc + j;  // the field f of joint j: a[3 * f]
      const V e = nx[3 * j] - sample[3 * j], u = nU[j], r = st[kU + j] - a[3 * kULow];
      const V fresh[9] = {a[3 * kCount] + 1,
                          a[3 * kSumE2] + e * e,
                          S::Max(a[3 * kMaxE], S::Abs(e)),
                          e,
                          a[3 * kTV] + S::Abs(u - st[kU + j]),
                          a[3 * kSumU2] + u * u,
                          S::Max(a[3 * kMaxU], S::Abs(u)),
                          st[kU + j] - r * c.decay,
                          a[3 * kSumHf2] + r * r * c.hf_weight};
      for (int g = 0; g < 9; g++) a[3 * g] = keep ? a[3 * g] : fresh[g];
      st[kWi + j] = keep ? st[kWi + j] : nw[j];
      st[kU + j] = keep ? st[kU + j] : u;
    }
  }
  for (int r = 0; r < kRows; r++) S::Store(out + r * N, st[r]);
}

template <typename T, int Rk4>
ffi::Error Run(ffi::ThreadPool& pool, const Consts<T>& c, int sw, int law, const T* ab, const T* table, int64_t L,
               int64_t R, const T* in, T* out, int64_t N) {
  const int64_t W = Simd<T>::W;
  fosmc::RunBlocks(pool, N / W, [=](int64_t i) {  // c by value: see RunBlocks
    Block<T, Rk4>(c, sw, law, ab + i * W, table, L, R, in + i * W, out + i * W, N);
  });
  return ffi::Error::Success();
}

template <typename T>
ffi::Error Dispatch(ffi::ThreadPool pool, ffi::AnyBuffer ab, ffi::AnyBuffer consts, ffi::AnyBuffer table,
                    ffi::AnyBuffer in, ffi::Result<ffi::AnyBuffer> out, int32_t rk4, int32_t sw, int32_t law) {
  // every check the Python side already makes, so that a misuse is an error, never a crash
  const auto type = in.element_type();
  if (ab.element_type() != type || consts.element_type() != type || table.element_type() != type ||
      out->element_type() != type)
    return ffi::Error::InvalidArgument("fosmc kernel: every buffer must have the carry's dtype");
  const auto dims = in.dimensions(), abd = ab.dimensions(), td = table.dimensions();
  if (dims.size() != 2 || dims[0] != kRows || abd.size() != 2 || abd[0] != 36 || abd[1] != dims[1] ||
      td.size() != 2 || td[1] != (rk4 ? 27 : 9) + 14 || out->element_count() != in.element_count() ||
      consts.element_count() != sizeof(Consts<T>) / sizeof(T))
    return ffi::Error::InvalidArgument("fosmc kernel: buffer shapes do not match the layout in kernel.cc");
  const int64_t N = dims[1], L = td[0], R = td[1];
  if (N % Simd<T>::W) return ffi::Error::InvalidArgument("fosmc kernel: the lane count must fill whole blocks");
  Consts<T> c;
  std::copy_n(consts.typed_data<T>(), sizeof(Consts<T>) / sizeof(T), reinterpret_cast<T*>(&c));
  const T *a = ab.typed_data<T>(), *tb = table.typed_data<T>(), *i = in.typed_data<T>();
  T* o = out->typed_data<T>();
  if (sw < 0 || sw > 3 || law < 0 || law > 1) return ffi::Error::InvalidArgument("fosmc kernel: unknown switching or law");
  if (rk4 == 0) return Run<T, 0>(pool, c, sw, law, a, tb, L, R, i, o, N);
  if (rk4 == 1) return Run<T, 1>(pool, c, sw, law, a, tb, L, R, i, o, N);
  return ffi::Error::InvalidArgument("fosmc kernel: unknown integrator");
}

ffi::Error Advance(ffi::ThreadPool pool, ffi::AnyBuffer ab, ffi::AnyBuffer consts, ffi::AnyBuffer table,
                   ffi::AnyBuffer in, ffi::Result<ffi::AnyBuffer> out, int32_t rk4, int32_t sw, int32_t law) {
  switch (in.element_type()) {
    case ffi::DataType::F32:
      return Dispatch<float>(pool, ab, consts, table, in, out, rk4, sw, law);
    case ffi::DataType::F64:
      return Dispatch<double>(pool, ab, consts, table, in, out, rk4, sw, law);
    default:
      return ffi::Error::InvalidArgument("fosmc kernel: float32 or float64 only");
  }
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(FosmcAdvance, Advance,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()  // ab
                                  .Arg<ffi::AnyBuffer>()  // consts
                                  .Arg<ffi::AnyBuffer>()  // table
                                  .Arg<ffi::AnyBuffer>()  // carry in
                                  .Ret<ffi::AnyBuffer>()  // carry out
                                  .Attr<int32_t>("rk4")
                                  .Attr<int32_t>("switching")
                                  .Attr<int32_t>("law"));
