// The skeleton of the generated kernels (fosmc_jax/_simulator/generated.py): the time loop, the
// blocks of lanes over XLA's thread pool, the checkpointed reverse sweep and the XLA FFI glue.
// No formula of the closed loop is here. Built once per precision (FOSMC_T) into a library of its
// own that runs every model: a model's library holds only its steps printed from the JAX model
// (fosmc_jax._simulator.codegen; files that define FOSMC_GEN_STEP and take the types and helpers
// below, not the skeleton), registered here with its layout (gen::Model) under an id its calls
// name. A model with derivatives has the step's vector-Jacobian product too, printed in two
// halves: the step that also stores its residuals (the n_res values the reverse reads) and the
// reverse from them.
//
// Layouts (rows of N lanes, lane-minor; T the model's float):
//   lanes  (nl_held + nl_sampled, N)  per rollout, what the steps take from the rollout's
//          parameters (hoisted out of the time loop by JAX): the held step's, then the sampled step's
//   table  (L, nt_held + nt_sampled)  per step k, what depends on time only (computed by JAX);
//          or (C, L, ...): C tables, each for N / C lanes in whole blocks (the c-th for lanes
//          [c N / C, (c + 1) N / C)), e.g. one per noise key (each key's own draws)
//   carry  (n, N)  the rollout's state, flat
//   ckpt   the carry at steps 0, K, 2K, ... (the forward stores them for the adjoint, which
//          recomputes each block's states from them), block-major: for each block of W lanes
//          (ceil(L / K), n, W). A block's checkpoints are one contiguous stream (rows of N
//          lanes scattered each step's few bytes over the whole buffer).
// Step k (from t_k to t_{k+1}, k counted from the call's k0) ends with a controller sample when
// (k0 + k + 1) % m == 0: the sampled step, else the held one (m = 1: the ideal loop).
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "vecmath.h"

namespace gen {

typedef FOSMC_T T;
typedef fosmc::Simd<T>::V V;
typedef decltype(V{} < V{}) M;
constexpr int W = fosmc::Simd<T>::W;

// A library function lane by lane; the type names the function, so that Lib can run the vector
// form where vecmath.h has one (tanh: the Coulomb friction, in every step of the arm)
constexpr bool Named(const char* a, const char* b) { return *a == *b && (*a == 0 || Named(a + 1, b + 1)); }
#define LIB(f)                                                 \
  [] {                                                         \
    struct F {                                                 \
      static constexpr bool Tanh() { return Named(#f, "tanh"); } \
      T operator()(T a) const { return std::f(a); }            \
    };                                                         \
    return F{};                                                \
  }()
#define LIB2(f) [](T a, T b) { return std::f(a, b); }

inline V Bc(T x) { return V{} + x; }
const M kTrue = V{} == V{}, kFalse = V{} != V{};
// XLA's max and min: NaN if either is NaN
inline V Max(V a, V b) { return a != a ? a : (b > a) | (b != b) ? b : a; }
inline V Min(V a, V b) { return a != a ? a : (b < a) | (b != b) ? b : a; }
inline V Abs(V x) { return fosmc::Simd<T>::Abs(x); }
inline V Sqrt(V x) { return fosmc::Simd<T>::Sqrt(x); }
inline V Sign(V x) { return x > Bc(0) ? Bc(1) : x < Bc(0) ? Bc(-1) : x; }
inline M IsFinite(V x) {
  const V d = x - x;  // 0 where finite, NaN at inf and NaN
  return d == d;
}
inline void SinCos(V x, V* s, V* c) { fosmc::SinCos<T>(x, s, c); }
template <typename F>
inline V Lib(V x, F f) {
  if constexpr (F::Tanh()) return fosmc::Tanh<T>(x);
  V r;
  for (int l = 0; l < W; l++) r[l] = f(x[l]);
  return r;
}
template <typename F>
inline V Lib2(V x, V y, F f) {
  V r;
  for (int l = 0; l < W; l++) r[l] = f(x[l], y[l]);
  return r;
}

}  // namespace gen

// A printed step's file (FOSMC_GEN_STEP) needs the types and helpers above only: without the
// skeleton it does not parse the XLA FFI header (seconds of each file's build).
#ifndef FOSMC_GEN_STEP

#include <sys/mman.h>

#include <algorithm>
#include <mutex>
#include <unordered_map>
#include <utility>
#include <vector>

#include "kernel.h"

namespace ffi = xla::ffi;

namespace gen {

// The functions a model's own library holds: its printed steps, held and sampled (the ideal
// loop's held one absent), and their halves of the vector-Jacobian product where it has them.
typedef void (*StepFn)(const V* x, const V* lv, const T* tv, V* y);
typedef void (*FwdFn)(const V* x, const V* lv, const T* tv, V* y, V* res);
typedef void (*BwdFn)(const V* x, const V* lv, const T* tv, const V* res, const V* ct, V* gx, V* glv);

// A model: its layout and its steps. One skeleton per precision runs every model (the skeleton is
// most of a build's time; a model's library is its printed steps alone), each call naming its
// model by the id it was registered under (fosmc_gen_register, from fosmc_jax: the "model"
// attribute). The layout's fields as generated.py's _Layout.
struct Model {
  int64_t n, nl_held, nl_sampled, nt_held, nt_sampled, m, n_res;
  const uint8_t* dynamic;  // n flags: the rows whose cotangent a truncation stops
  StepFn held, sampled;
  FwdFn held_fwd, sampled_fwd;
  BwdFn held_bwd, sampled_bwd;
  int64_t nl() const { return nl_held + nl_sampled; }
  int64_t nt() const { return nt_held + nt_sampled; }
};

inline std::mutex g_models_mutex;
inline std::unordered_map<int64_t, std::pair<Model, std::vector<uint8_t>>> g_models;  // with their own flags

inline const Model* Find(int64_t id) {
  std::lock_guard<std::mutex> lock(g_models_mutex);
  auto it = g_models.find(id);
  return it == g_models.end() ? nullptr : &it->second.first;  // entries are never erased: the pointer stays
}

inline void Step(const Model& mo, int64_t k, const V* x, const V* lv, const T* row, V* y) {
  if (mo.m == 1 || k % mo.m == 0)
    mo.sampled(x, lv + mo.nl_held, row + mo.nt_held, y);
  else
    mo.held(x, lv, row, y);
}

// The step that also stores its residuals (what its reverse reads) in res, and its reverse from them
inline void StepRes(const Model& mo, int64_t k, const V* x, const V* lv, const T* row, V* y, V* res) {
  if (mo.m == 1 || k % mo.m == 0)
    mo.sampled_fwd(x, lv + mo.nl_held, row + mo.nt_held, y, res);
  else
    mo.held_fwd(x, lv, row, y, res);
}

inline void StepBwd(const Model& mo, int64_t k, const V* x, const V* lv, const T* row, const V* res, const V* ct,
                    V* gx, V* glv) {
  if (mo.m == 1 || k % mo.m == 0)
    mo.sampled_bwd(x, lv + mo.nl_held, row + mo.nt_held, res, ct, gx, glv + mo.nl_held);
  else
    mo.held_bwd(x, lv, row, res, ct, gx, glv);
}

struct Shape {
  int64_t N, L, K, k0, per;  // per: the lanes that read one table
};

// One block of W lanes at column c: L steps from `in` to `out`, the carry stored every K steps
// into `ckpt` where it is given.
inline void Forward(const Model& mo, const Shape& s, const T* lanes, const T* table, const T* in, T* out, T* ckpt,
                    int64_t c) {
  const int64_t n = mo.n, nl = mo.nl(), nt = mo.nt();
  std::vector<V> buf(2 * n + nl);
  V *x = buf.data(), *y = x + n, *lv = y + n;
  for (int64_t r = 0; r < n; r++) x[r] = fosmc::Simd<T>::Load(in + r * s.N + c);
  for (int64_t r = 0; r < nl; r++) lv[r] = fosmc::Simd<T>::Load(lanes + r * s.N + c);
  table += (c / s.per) * s.L * nt;  // this block's table
  if (ckpt) ckpt += c * ((s.L + s.K - 1) / s.K) * n;  // this block's
  for (int64_t k = 0; k < s.L; k++) {
    if (ckpt && k % s.K == 0)
      for (int64_t r = 0; r < n; r++) fosmc::Simd<T>::Store(ckpt + ((k / s.K) * n + r) * W, x[r]);
    Step(mo, s.k0 + k + 1, x, lv, table + k * nt, y);
    std::swap(x, y);
  }
  for (int64_t r = 0; r < n; r++) fosmc::Simd<T>::Store(out + r * s.N + c, x[r]);
}

// The reverse sweep of one block: from the cotangent of the last carry, the cotangents of the
// first carry and of the lanes (summed over the steps). Each block of K steps is recomputed from
// its checkpoint, each step storing its residuals (a block's stay in the core's cache), then
// swept backwards from them. `truncate` (> 0): at every step k with k % truncate == 0 the
// cotangent of the dynamic rows (Model::dynamic) stops: truncated backpropagation through time.
inline void Adjoint(const Model& mo, const Shape& s, int64_t truncate, const T* lanes, const T* table, const T* ckpt,
                    const T* ct_out, T* ct_in, T* ct_lanes, int64_t c) {
  const int64_t n = mo.n, nl = mo.nl(), nt = mo.nt();
  std::vector<V> buf(2 * nl + 2 * n);
  V *lv = buf.data(), *glv = lv + nl, *g = glv + nl, *gx = g + n;  // g, gx: a step's end and start, swapped
  for (int64_t r = 0; r < nl; r++) lv[r] = fosmc::Simd<T>::Load(lanes + r * s.N + c), glv[r] = V{};
  for (int64_t r = 0; r < n; r++) g[r] = fosmc::Simd<T>::Load(ct_out + r * s.N + c);
  const int64_t K = std::min(s.K, s.L);
  std::vector<V> states(static_cast<size_t>(K + 1) * n), res(static_cast<size_t>(K) * mo.n_res);
  ckpt += c * ((s.L + s.K - 1) / s.K) * n;  // this block's
  table += (c / s.per) * s.L * nt;
  for (int64_t j = (s.L + s.K - 1) / s.K - 1; j >= 0; j--) {
    const int64_t k1 = j * s.K, k2 = std::min(s.L, k1 + s.K);
    V *st = states.data(), *rs = res.data();
    for (int64_t r = 0; r < n; r++) st[r] = fosmc::Simd<T>::Load(ckpt + (j * n + r) * W);
    for (int64_t k = k1; k < k2; k++)
      StepRes(mo, s.k0 + k + 1, st + (k - k1) * n, lv, table + k * nt, st + (k - k1 + 1) * n, rs + (k - k1) * mo.n_res);
    for (int64_t k = k2 - 1; k >= k1; k--) {
      StepBwd(mo, s.k0 + k + 1, st + (k - k1) * n, lv, table + k * nt, rs + (k - k1) * mo.n_res, g, gx, glv);
      if (truncate > 0 && (s.k0 + k) % truncate == 0)
        for (int64_t r = 0; r < n; r++) gx[r] = mo.dynamic[r] ? V{} : gx[r];
      std::swap(g, gx);
    }
  }
  for (int64_t r = 0; r < n; r++) fosmc::Simd<T>::Store(ct_in + r * s.N + c, g[r]);
  for (int64_t r = 0; r < nl; r++) fosmc::Simd<T>::Store(ct_lanes + r * s.N + c, glv[r]);
}

inline ffi::Error Check(int64_t id, ffi::AnyBuffer lanes, ffi::AnyBuffer table, ffi::AnyBuffer carry, Shape* s,
                        int64_t K, const Model** mo, bool adjoint) {
  *mo = Find(id);
  if (!*mo || (adjoint && !(*mo)->sampled_bwd))
    return ffi::Error::InvalidArgument("fosmc generated kernel: the call's model is not registered in this process");
  const auto type = sizeof(T) == 8 ? ffi::DataType::F64 : ffi::DataType::F32;
  const auto ld = lanes.dimensions(), td = table.dimensions(), cd = carry.dimensions();
  if (lanes.element_type() != type || table.element_type() != type || carry.element_type() != type)
    return ffi::Error::InvalidArgument("fosmc generated kernel: every buffer must have the model's dtype");
  const size_t tn = td.size();
  if (ld.size() != 2 || (tn != 2 && tn != 3) || cd.size() != 2 || cd[0] != (*mo)->n || ld[0] != (*mo)->nl() ||
      ld[1] != cd[1] || td[tn - 1] != (*mo)->nt())
    return ffi::Error::InvalidArgument("fosmc generated kernel: buffer shapes do not match the model's layout");
  const int64_t tables = tn == 3 ? td[0] : 1;
  if (tables < 1 || cd[1] % tables || (cd[1] / tables) % W)
    return ffi::Error::InvalidArgument("fosmc generated kernel: each table's lanes must fill whole blocks");
  if (K < 1) return ffi::Error::InvalidArgument("fosmc generated kernel: the checkpoint interval must be positive");
  *s = Shape{cd[1], td[tn - 2], K, 0, cd[1] / tables};
  return ffi::Error::Success();
}

// Asks the kernel for huge pages on a fresh buffer of `bytes` (XLA maps one anew per call for the
// checkpoints, tens of MB): faulting it in 4 KiB pages cost about a tenth of a value and gradient.
inline void HugePages(void* p, size_t bytes) {
  constexpr uintptr_t kHuge = uintptr_t{1} << 21;
  const uintptr_t a = (reinterpret_cast<uintptr_t>(p) + kHuge - 1) & ~(kHuge - 1);
  const uintptr_t e = (reinterpret_cast<uintptr_t>(p) + bytes) & ~(kHuge - 1);
  if (e > a) madvise(reinterpret_cast<void*>(a), e - a, MADV_HUGEPAGE);  // advice only: a refusal is harmless
}

inline ffi::Error RunForward(ffi::ThreadPool pool, ffi::AnyBuffer lanes, ffi::AnyBuffer table, ffi::AnyBuffer in,
                             ffi::Result<ffi::AnyBuffer> out, T* ckpt, int64_t k0, int64_t K, int64_t id) {
  Shape s;
  const Model* mo;
  if (auto e = Check(id, lanes, table, in, &s, K, &mo, false); e.failure()) return e;
  s.k0 = k0;
  const T *lp = lanes.typed_data<T>(), *tp = table.typed_data<T>(), *ip = in.typed_data<T>();
  T* op = out->typed_data<T>();
  fosmc::RunBlocks(pool, s.N / W, [=](int64_t i) { Forward(*mo, s, lp, tp, ip, op, ckpt, i * W); });
  return ffi::Error::Success();
}

inline ffi::Error GenForward(ffi::ThreadPool pool, ffi::AnyBuffer lanes, ffi::AnyBuffer table, ffi::AnyBuffer in,
                             ffi::Result<ffi::AnyBuffer> out, int64_t k0, int64_t id) {
  return RunForward(pool, lanes, table, in, out, nullptr, k0, 1, id);
}

inline ffi::Error GenForwardCk(ffi::ThreadPool pool, ffi::AnyBuffer lanes, ffi::AnyBuffer table, ffi::AnyBuffer in,
                               ffi::Result<ffi::AnyBuffer> out, ffi::Result<ffi::AnyBuffer> ckpt, int64_t k0,
                               int64_t K, int64_t id) {
  HugePages(ckpt->untyped_data(), ckpt->size_bytes());
  return RunForward(pool, lanes, table, in, out, ckpt->typed_data<T>(), k0, K, id);
}

inline ffi::Error GenAdjoint(ffi::ThreadPool pool, ffi::AnyBuffer lanes, ffi::AnyBuffer table, ffi::AnyBuffer ckpt,
                             ffi::AnyBuffer ct_out, ffi::Result<ffi::AnyBuffer> ct_in,
                             ffi::Result<ffi::AnyBuffer> ct_lanes, int64_t k0, int64_t K, int64_t truncate,
                             int64_t id) {
  Shape s;
  const Model* mo;
  if (auto e = Check(id, lanes, table, ct_out, &s, K, &mo, true); e.failure()) return e;
  s.k0 = k0;
  if (ckpt.element_count() != ((s.L + K - 1) / K) * mo->n * s.N)
    return ffi::Error::InvalidArgument("fosmc generated kernel: the checkpoints do not match the horizon");
  const T *lp = lanes.typed_data<T>(), *tp = table.typed_data<T>(), *cp = ckpt.typed_data<T>(),
          *gp = ct_out.typed_data<T>();
  T *ip = ct_in->typed_data<T>(), *glp = ct_lanes->typed_data<T>();
  fosmc::RunBlocks(pool, s.N / W, [=](int64_t i) { Adjoint(*mo, s, truncate, lp, tp, cp, gp, ip, glp, i * W); });
  return ffi::Error::Success();
}

}  // namespace gen

// The skeleton's library (one per precision): the registry's entry point and the three handlers.
extern "C" void fosmc_gen_register(int64_t id, const gen::Model* mo) {
  std::lock_guard<std::mutex> lock(gen::g_models_mutex);
  auto& entry = gen::g_models[id];
  entry.second.assign(mo->dynamic, mo->dynamic + mo->n);
  entry.first = *mo;
  entry.first.dynamic = entry.second.data();
}

XLA_FFI_DEFINE_HANDLER_SYMBOL(FosmcGenForward, gen::GenForward,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Attr<int64_t>("k0")
                                  .Attr<int64_t>("model"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(FosmcGenForwardCk, gen::GenForwardCk,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Attr<int64_t>("k0")
                                  .Attr<int64_t>("K")
                                  .Attr<int64_t>("model"));

XLA_FFI_DEFINE_HANDLER_SYMBOL(FosmcGenAdjoint, gen::GenAdjoint,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Ret<ffi::AnyBuffer>()
                                  .Attr<int64_t>("k0")
                                  .Attr<int64_t>("K")
                                  .Attr<int64_t>("truncate")
                                  .Attr<int64_t>("model"));

#endif  // FOSMC_GEN_STEP
