// The arm's closed loop as one XLA FFI kernel for the CPU (fosmc_jax/_simulator/native.py builds it with
// the host's C++ compiler, fosmc_jax/_simulator/arm_native.py calls it).
//
// It advances L steps of fosmc_jax._simulator.rollout.simulate for N independent rollouts ("lanes") of
// the 3-DOF arm (fosmc_jax._plants.arm: the closed form M, C q', G of ``_inertia`` / ``_coriolis``,
// the adjugate solve, BLDC motors L i' = u - R i - Kb q', Coulomb friction Fc tanh(q'/v_c) and the
// external torque tau_bias + tau_step [t >= t_step] + tau_sin sin(2 pi f_sin t) at the stage times)
// in one of two loops:
//   ideal    (Digital = 0): the law from the exact state at every step, its state integrated
//                           with the plant: fosmc_jax.FOSMC ((14), (23) or the equivalent law,
//                           switching (28), sign, sat or tanh), fosmc_jax.SMC or
//                           fosmc_jax.ContinuousSuperTwisting;
//   digital  (Digital = 1): fosmc_jax.DigitalLoop around fosmc_jax.DiscreteFOSMC, SMC or
//                           SuperTwisting: the law every m-th step from the encoder's quantized
//                           angles and measured or differenced rates, a delay line of d samples
//                           and the voltage limit.
// Euler or RK4, float or double, the divergence guard and every running metric of
// fosmc_jax._simulator.metrics. The operations are those of the JAX functions named beside them, in the
// same order (no FMA: -ffp-contract=off), except that the accelerations of a state, computed
// when it is observed, are kept for the next step's first stage (the same state: the same
// numbers), and that SMC's and super-twisting's solves with CB are products with (CB)^-1.
// tests/test_arm_native.py holds this copy to the JAX model at random states, arms and gains,
// and over whole rollouts of every loop and law against vmap(simulate).
//
// Every parameter is per lane (the arm's, the law's, the loop's), so a batch may mix payloads,
// arms and candidate controllers (the tuner's chunks are one call). What depends on time only
// comes in a table computed by JAX, so any reference works.
//
// Layouts (T = float or double; rows of N lanes, lane-minor):
//   lanes   (156, N)  the arm (52: payload, d2, d3, l2, l3, c2, c3, m2, m3, I1, I2 (3), I3 (3),
//                     Jm (3), F (3), g, R (3), L (3), Kt (3), Kb (3), Fc (3), v_c, tau_bias (3),
//                     tau_step (3), t_step, tau_sin (3), f_sin (3): fosmc_jax.ArmParams' fields
//                     but d1, in order), the law (96: see Law),
//                     the loop (the encoder's step 2 pi / counts (3; 0: none), u_max (3; inf:
//                     none), the loop's period T (the estimator's)) and the law's period
//   consts  (4,)      dt, the low-pass's decay and weight over a step (chattering_hf), the bound
//   table   (L, R)    per step k: X_d at the integrator's stage times (ideal loop only: t_k; or
//                     t_k, t_k + dt/2, t_k + dt for RK4; 9 each), then at t' = (k + 1) dt: X_d
//                     (9), Omega (3), ||X_d||, ||Omega||, t', 1 where t' is a sample (else 0),
//                     the reference's third derivatives (3), t_k = k dt (20 in all)
//   carry   (56 + 3d, N)  q (3), q' (3), i (3), q'' (3), the law's state (the FOSMC's w,
//                     super-twisting's v) (3), U (3), the estimator's memory (theta (3),
//                     theta' (3)), the accumulator's 10 fields x 3 joints (field-major, as
//                     fosmc_jax._simulator.metrics.Accumulator), diverged (0 / 1), diverged_at, the delay
//                     line (d x 3, oldest first)
#include <limits>

#include "kernel.h"
#include "vecmath.h"
#include "layout.h"  // generated from the Python side (fosmc_jax._simulator.native.layout_header)

namespace ffi = xla::ffi;

namespace {

using fosmc::Simd;
using fosmc::SinCos;
using fosmc::Tanh;
using fosmc::All;
using namespace fosmc::acc;  // the accumulator's fields
constexpr int kLaneRows = fosmc::arm::kLaneRows, kCarryRows = fosmc::arm::kCarryRows,
              kSampleCols = fosmc::arm::kSampleCols, kMaxDelay = 8;
static_assert(kSampleCols == 20, "layout.h: the table's sample columns changed; update Block's reads of them");
enum { kQ = 0, kDq = 3, kCur = 6, kAcc = 9, kW = 12, kU = 15, kMemTh = 18, kMemDth = 21, kMet = fosmc::arm::kMet,
       kDiv = fosmc::arm::kDiv, kDivAt = fosmc::arm::kDivAt, kPending = fosmc::arm::kCarryRows };
static_assert(kMet == kMemDth + 3, "layout.h: the accumulator follows the estimator's memory");
static_assert(kFields == 10, "layout.h: the accumulator's fields changed; update Block's update of them");

template <typename T>
using V = typename Simd<T>::V;

// The lane rows, in order (every member one vector: the struct is the rows' image).
template <typename T>
struct Lane {
  V<T> payload, d2, d3, l2, l3, c2, c3, m2, m3, I1, I2[3], I3[3], Jm[3], F[3], g, R[3], L[3], Kt[3], Kb[3];
  V<T> Fc[3], v_c, tau_bias[3], tau_step[3], t_step, tau_sin[3], f_sin[3];
  V<T> C[27], S[27], CBi[9], K[27], gamma[3], delta[3], q[3], u_max[3], T_, T_law;
};

template <typename T>
struct How {
  T dt, decay, hf_weight, bound;
  int kind, sw, law, difference, delay;
};


// Which of the optional terms a block computes: skipped where every lane of the block has them
// zero (Fc = 0: Fc tanh(.) = 0 exactly; tau_sin = 0: tau_sin sin(.) = 0; no external torque at
// all: d = 0), so that an arm without them pays nothing for them; the results are the same.
template <typename T>
struct Terms {
  bool coulomb, external, sinus;
  V<T> inv_v;  // 1 / v_c, once per block (_terms multiplies the rates by it)
};

// The external torque at time t: fosmc_jax._plants.arm._external, in its order.
template <typename T>
inline void External(const Lane<T>& p, const Terms<T>& on, T t, V<T> d[3]) {
  using W = V<T>;
  const W zero = {}, tt = zero + t;
  if (!on.external) {
    for (int j = 0; j < 3; j++) d[j] = zero;
    return;
  }
  const auto stepped = tt >= p.t_step;
  for (int j = 0; j < 3; j++) d[j] = p.tau_bias[j] + (stepped ? p.tau_step[j] : zero);
  if (!on.sinus) return;
  const T two_pi = static_cast<T>(2 * M_PI);
  for (int j = 0; j < 3; j++) {
    W s, c;
    SinCos<T>((two_pi * p.f_sin[j]) * tt, &s, &c);  // |2 pi f t| < 2^20: f t below 1.6e5 periods
    d[j] = d[j] + p.tau_sin[j] * s;
  }
}

// theta'' = M^-1 (Kt i - (C q' + G + F q' + Fc tanh(q' (1/v_c))) + d), d the external torque:
// fosmc_jax._plants.arm._accelerations (_inertia, _coriolis, _terms, _solve_sym), term by term in
// their order.
template <typename T>
inline void Accelerations(const Lane<T>& p, const Terms<T>& on, const V<T> q[3], const V<T> dq[3], const V<T> cur[3],
                          const V<T> d[3], V<T> out[3]) {
  using W = V<T>;
  W s2, c2, s3, c3;
  SinCos<T>(q[1], &s2, &c2);
  SinCos<T>(q[2], &s3, &c3);
  const W s23 = s2 * c3 + c2 * s3, c23 = c2 * c3 - s2 * s3;
  W m11 = p.I1 + p.Jm[0] + p.I2[0] * s2 * s2 + p.I2[2] * c2 * c2 + p.I3[0] * s23 * s23 + p.I3[2] * c23 * c23;
  W m22 = p.Jm[1] + p.I2[1] + p.I3[1], m23 = p.I3[1], m33 = p.Jm[2] + p.I3[1];
  W b11 = 2 * (p.I3[0] - p.I3[2]) * s23 * c23;
  W a11 = 2 * (p.I2[0] - p.I2[2]) * s2 * c2 + b11;
  // link 2: (m2, c2, -, d2), its mass on the shoulder's axis only (_point_masses)
  W x = p.c2 * s2, dx2 = p.c2 * c2;
  m11 = m11 + p.m2 * (x * x + p.d2 * p.d2);
  a11 = a11 + 2 * p.m2 * x * dx2;
  W m12 = p.m2 * p.d2 * dx2, a12 = -(p.m2 * p.d2 * x);
  m22 = m22 + p.m2 * p.c2 * p.c2;
  W g2 = p.m2 * x, g3, m13, a13, b12, b22, b23;
  // link 3 (m3, l2, c3, d2 + d3), then the payload (payload, l2, l3, d2 + d3)
  const W y = p.d2 + p.d3;
  for (int body = 0; body < 2; body++) {
    const W m = body ? p.payload : p.m3, a = p.l2, b = body ? p.l3 : p.c3;
    const W bs = b * s23, bc = b * c23;
    x = a * s2 + bs, dx2 = a * c2 + bc;
    const W dx3 = bc, mx = m * x, my = m * y, mab = m * a * b;
    m11 = m11 + m * (x * x + y * y), a11 = a11 + 2 * mx * dx2, b11 = b11 + 2 * mx * dx3;
    m12 = m12 + my * dx2, a12 = a12 - my * x;
    m22 = m22 + m * (a * a + b * b) + 2 * mab * c3;
    m23 = m23 + m * b * b + mab * c3;
    m33 = m33 + m * b * b;
    g2 = g2 + mx;
    if (body == 0) {
      b12 = -(my * bs), m13 = my * dx3, a13 = -(my * bs), b22 = -(2 * mab * s3), b23 = -(mab * s3), g3 = m * bs;
    } else {
      b12 = b12 - my * bs, m13 = m13 + my * dx3, a13 = a13 - my * bs, b22 = b22 - 2 * mab * s3;
      b23 = b23 - mab * s3, g3 = g3 + m * bs;
    }
  }
  g2 = p.g * g2, g3 = p.g * g3;
  const W b13 = a13;
  // C q' = M' q' - 1/2 d/dq (q'^T M q') (_coriolis)
  const W w1 = dq[0], w2 = dq[1], w3 = dq[2];
  const W e11 = a11 * w2 + b11 * w3, e12 = a12 * w2 + b12 * w3, e13 = a13 * w2 + b13 * w3;
  const W e22 = b22 * w3, e23 = b23 * w3;
  const W h2 = w1 * (a11 * w1 / 2 + a12 * w2 + a13 * w3);
  const W h3 = w1 * (b11 * w1 / 2 + b12 * w2 + b13 * w3) + w2 * (b22 * w2 / 2 + b23 * w3);
  W n1 = e11 * w1 + e12 * w2 + e13 * w3 + p.F[0] * w1;
  W n2 = e12 * w1 + e22 * w2 + e23 * w3 - h2 + g2 + p.F[1] * w2;
  W n3 = e13 * w1 + e23 * w2 - h3 + g3 + p.F[2] * w3;
  if (on.coulomb) {
    n1 = n1 + p.Fc[0] * Tanh<T>(w1 * on.inv_v);
    n2 = n2 + p.Fc[1] * Tanh<T>(w2 * on.inv_v);
    n3 = n3 + p.Fc[2] * Tanh<T>(w3 * on.inv_v);
  }
  const W r1 = p.Kt[0] * cur[0] - n1 + d[0], r2 = p.Kt[1] * cur[1] - n2 + d[1], r3 = p.Kt[2] * cur[2] - n3 + d[2];
  // _solve_sym: the adjugate over the determinant
  const W A = m22 * m33 - m23 * m23, B = m13 * m23 - m12 * m33, C = m12 * m23 - m13 * m22;
  const W E = m11 * m33 - m13 * m13, Fm = m12 * m13 - m11 * m23, I = m11 * m22 - m12 * m12;
  const W inv_det = 1 / (m11 * A + m12 * B + m13 * C);
  out[0] = (A * r1 + B * r2 + C * r3) * inv_det;
  out[1] = (B * r1 + E * r2 + Fm * r3) * inv_det;
  out[2] = (C * r1 + Fm * r2 + I * r3) * inv_det;
}

// M v for a 3 x 9 matrix of lane rows and 9 lane values (fosmc_jax's ``C @ Z``)
template <typename T>
inline void Mv39(const V<T>* m, const V<T>* v, V<T>* out) {
  for (int j = 0; j < 3; j++) {
    V<T> a = m[9 * j] * v[0];
    for (int i = 1; i < 9; i++) a += m[9 * j + i] * v[i];
    out[j] = a;
  }
}

// Sign, as jnp.sign (0 at 0, NaN stays)
template <typename T>
inline V<T> Sign(V<T> x) {
  const V<T> zero = {};
  return x > 0 ? zero + 1 : (x < 0 ? zero - 1 : x);
}

// The law at a sample from the measurement Y and Z = Y - X_d, with ``w`` the law's state (the
// FOSMC's integral, super-twisting's v); ``smp`` is the table's sample block. Gives U, s and the
// state after the sample (the sampled laws' sums; the ideal loop integrates its state instead).
//   FOSMC (h.kind 0): s = C Z - w (14), U = Omega - (CB)^-1 rho f(s) (23) (+ K Z for the
//     equivalent law), rho = gamma_1 ||Z|| + gamma_2 ||X_d|| + gamma_3 ||Omega||
//     (fosmc_jax._controllers.fosmc.control_law); DiscreteFOSMC: w + T S Z.
//   SMC (1) and super-twisting (2) (fosmc_jax._controllers.smc): s = C Z, U_eq = (CB)^-1 (C X_d' - C X'(Y)),
//     X'(Y) the nominal model's rates; U = U_eq - (CB)^-1 k sat(s / phi), or
//     U = U_eq - (CB)^-1 (k1 |s|^(1/2) sign(s) - v) and v - T k2 sign(s).
// Lanes: C, then S (FOSMC) or the nominal rows a_rows (SMC, super-twisting), (CB)^-1, gamma
// (FOSMC) or k, k1, delta (FOSMC) or phi, k2, and the law's period.
template <typename T, int Digital>
inline void Law(const Lane<T>& p, const How<T>& h, const V<T> Y[9], const V<T> Z[9], const V<T> w[3], const T* smp,
                V<T> U[3], V<T> s[3], V<T> nw[3]) {
  using W = V<T>;
  using S = Simd<T>;
  const W zero = {};
  W f[3], cz[3];
  Mv39<T>(p.C, Z, cz);
  if (h.kind == 0) {
    W zz = Z[0] * Z[0];
    for (int i = 1; i < 9; i++) zz += Z[i] * Z[i];
    const W rho = p.gamma[0] * (zz > 0 ? S::Sqrt(zz) : zero) + p.gamma[1] * smp[12] + p.gamma[2] * smp[13];
    for (int j = 0; j < 3; j++) {
      s[j] = cz[j] - w[j];
      const W d = p.delta[j];
      W sw;  // the switching function: h.sw is its position in fosmc_jax._controllers.fosmc.SWITCHING
      if (h.sw == 0) sw = Sign<T>(s[j]);
      else if (h.sw == 1) sw = s[j] / (S::Abs(s[j]) + d);
      else if (h.sw == 2) sw = S::Min(S::Max(s[j] / d, zero - 1), zero + 1);
      else sw = S::Map(s[j] / d, [](T a) { return std::tanh(a); });
      f[j] = rho * sw;
    }
    W kz[3];
    if (h.law == 1) Mv39<T>(p.K, Z, kz);
    for (int j = 0; j < 3; j++) {
      U[j] = smp[9 + j] - (p.CBi[3 * j] * f[0] + p.CBi[3 * j + 1] * f[1] + p.CBi[3 * j + 2] * f[2]);
      if (h.law == 1) U[j] = U[j] + kz[j];
    }
    if constexpr (Digital) {
      W sz[3];
      Mv39<T>(p.S, Z, sz);
      for (int j = 0; j < 3; j++) nw[j] = w[j] + p.T_law * sz[j];
    } else {
      for (int j = 0; j < 3; j++) nw[j] = w[j];
    }
    return;
  }
  // fosmc_jax._controllers.smc._surface: C X_d' - C X'(Y), X'(Y) = (Y2, Y3, a_rows Y, ...) per joint
  W jerk[3], rates[9], e[3], ueq[3];
  Mv39<T>(p.S, Y, jerk);
  for (int j = 0; j < 3; j++) rates[3 * j] = Y[3 * j + 1], rates[3 * j + 1] = Y[3 * j + 2], rates[3 * j + 2] = jerk[j];
  const T xd1[9] = {smp[1], smp[2], smp[16], smp[4], smp[5], smp[17], smp[7], smp[8], smp[18]};  // X_d'
  W cr[3];
  Mv39<T>(p.C, rates, cr);
  for (int j = 0; j < 3; j++) {
    W cd = p.C[9 * j] * xd1[0];
    for (int i = 1; i < 9; i++) cd += p.C[9 * j + i] * xd1[i];
    e[j] = cd - cr[j];
  }
  for (int j = 0; j < 3; j++) {
    s[j] = cz[j];
    ueq[j] = p.CBi[3 * j] * e[0] + p.CBi[3 * j + 1] * e[1] + p.CBi[3 * j + 2] * e[2];
    if (h.kind == 1) {
      f[j] = p.gamma[j] * S::Min(S::Max(s[j] / p.delta[j], zero - 1), zero + 1);
      nw[j] = w[j];
    } else {
      const W a = S::Abs(s[j]);
      f[j] = p.gamma[j] * ((a > 0 ? S::Sqrt(a) : zero) * Sign<T>(s[j])) - w[j];
      nw[j] = w[j] - p.T_law * p.delta[j] * Sign<T>(s[j]);
    }
  }
  for (int j = 0; j < 3; j++) U[j] = ueq[j] - (p.CBi[3 * j] * f[0] + p.CBi[3 * j + 1] * f[1] + p.CBi[3 * j + 2] * f[2]);
}

template <typename T, int Rk4, int Digital>
void Block(const How<T>& h, const T* lanes, const T* table, int64_t L, int64_t R, const T* in, T* out, int64_t N,
           int64_t rows) {
  using S = Simd<T>;
  using W = V<T>;
  Lane<T> p;
  static_assert(sizeof(Lane<T>) == kLaneRows * sizeof(W), "the lane rows' image");
  for (int r = 0; r < kLaneRows; r++) reinterpret_cast<W*>(&p)[r] = S::Load(lanes + r * N);
  W st[kCarryRows + 3 * kMaxDelay];
  for (int64_t r = 0; r < rows; r++) st[r] = S::Load(in + r * N);
  const T dt = h.dt, half = h.dt / 2, big = std::numeric_limits<T>::max();
  const W zero = {};
  const int stages = Digital ? 0 : (Rk4 ? 3 : 1);
  // d/dt of (q, q', i) and, in the ideal loop, of the law's state: fosmc_jax._plants.arm.Arm.derivative,
  // FOSMC.derivative (w' = S (X - X_d(t)), X = (q, q', q'') per joint), ContinuousSuperTwisting's
  // (v' = -k2 sign(C (X - X_d(t)))); SMC has none (0)
  auto field = [&](const W* q, const W* dq, const W* cur, const W* acc, const W* U, const T* xd, W* dcur, W* dw) {
    for (int j = 0; j < 3; j++) dcur[j] = (U[j] - p.R[j] * cur[j] - p.Kb[j] * dq[j]) / p.L[j];
    if constexpr (!Digital) {
      W z[9];
      for (int j = 0; j < 3; j++) z[3 * j] = q[j] - xd[3 * j], z[3 * j + 1] = dq[j] - xd[3 * j + 1], z[3 * j + 2] = acc[j] - xd[3 * j + 2];
      if (h.kind == 0) Mv39<T>(p.S, z, dw);
      if (h.kind == 1)
        for (int j = 0; j < 3; j++) dw[j] = zero;
      if (h.kind == 2) {
        Mv39<T>(p.C, z, dw);
        for (int j = 0; j < 3; j++) dw[j] = -p.delta[j] * Sign<T>(dw[j]);
      }
    }
  };
  // the optional terms of this block's arms (Terms)
  Terms<T> on{false, false, false, 1 / p.v_c};
  for (int l = 0; l < S::W; l++)
    for (int j = 0; j < 3; j++) {
      on.coulomb |= p.Fc[j][l] != 0, on.sinus |= p.tau_sin[j][l] != 0;
      on.external |= p.tau_bias[j][l] != 0 || p.tau_step[j][l] != 0 || p.tau_sin[j][l] != 0;
    }
  for (int64_t k = 0; k < L; k++) {
    const T* row = table + k * R;
    const T* smp = row + 9 * stages;  // X_d, Omega, ||X_d||, ||Omega||, t', sample?, X_d''', t_k
    const T t0 = smp[19];  // the stages at t_k, t_k + dt/2, t_k + dt (rollout._rk4's); observed at t'
    W d[3];                // the external torque at a stage's time
    const W *q = st + kQ, *dq = st + kDq, *cur = st + kCur, *acc = st + kAcc, *w = st + kW, *U = st + kU;
    W nq[3], ndq[3], ncur[3], nw[3], nacc[3], nU[3], dc[3], dw[3];
    // the integrator step from t_k with U held (fosmc_jax._simulator.step._euler / _rk4); acc are the
    // accelerations of this state, computed when it was observed
#ifdef FOSMC_NO_REUSE  // an ablation (benchmarks/arm_levers.py): the accelerations recomputed
    W acc0[3];
    External<T>(p, on, t0, d);
    Accelerations<T>(p, on, q, dq, cur, d, acc0);
    acc = acc0;
#endif
    field(q, dq, cur, acc, U, row, dc, dw);
    if constexpr (!Rk4) {
      for (int j = 0; j < 3; j++) {
        nq[j] = q[j] + dt * dq[j], ndq[j] = dq[j] + dt * acc[j], ncur[j] = cur[j] + dt * dc[j];
        if constexpr (!Digital) nw[j] = w[j] + dt * dw[j];
      }
    } else {
      // k_i = (q', q'', i', w') at the stages; the sums k1 + 2 k2 + 2 k3 + k4 in that order
      W sq[3], sa[3], sc[3], sw[3], yq[3], ydq[3], yc[3], yw[3], ya[3];
      for (int j = 0; j < 3; j++) {
        sq[j] = dq[j], sa[j] = acc[j], sc[j] = dc[j], sw[j] = Digital ? zero : dw[j];
        yq[j] = q[j] + half * dq[j], ydq[j] = dq[j] + half * acc[j], yc[j] = cur[j] + half * dc[j];
        if constexpr (!Digital) yw[j] = w[j] + half * dw[j];
      }
      for (int stg = 1; stg < 4; stg++) {
        if (stg != 2) External<T>(p, on, stg < 3 ? t0 + half : t0 + dt, d);  // stage 2: stage 1's time
        Accelerations<T>(p, on, yq, ydq, yc, d, ya);
        field(yq, ydq, yc, ya, U, row + 9 * (stg < 3 ? 1 : 2), dc, dw);
        const T wt = stg < 3 ? 2 : 1, hn = stg < 2 ? half : dt;
        for (int j = 0; j < 3; j++) {
          sq[j] += wt * ydq[j], sa[j] += wt * ya[j], sc[j] += wt * dc[j];
          if constexpr (!Digital) sw[j] += wt * dw[j];
          if (stg < 3) {
            yq[j] = q[j] + hn * ydq[j], ydq[j] = dq[j] + hn * ya[j], yc[j] = cur[j] + hn * dc[j];
            if constexpr (!Digital) yw[j] = w[j] + hn * dw[j];
          }
        }
      }
      for (int j = 0; j < 3; j++) {
        nq[j] = q[j] + dt * (sq[j] / 6), ndq[j] = dq[j] + dt * (sa[j] / 6), ncur[j] = cur[j] + dt * (sc[j] / 6);
        if constexpr (!Digital) nw[j] = w[j] + dt * (sw[j] / 6);
      }
    }
    // observe at t' = (k + 1) dt: RK4's last stage was at t_k + dt, the same time but for rounding
    if (!(Rk4 && smp[14] == t0 + dt)) External<T>(p, on, smp[14], d);
    Accelerations<T>(p, on, nq, ndq, ncur, d, nacc);
    // the check of _simulator._finite_and_bounded on what this step changes (the rest was checked)
    auto ok = S::Abs(nq[0]) <= h.bound;  // a lane mask; NaN fails every comparison
    for (int j = 0; j < 3; j++)
      ok &= (S::Abs(nq[j]) <= h.bound) & (S::Abs(ndq[j]) <= h.bound) & (S::Abs(nacc[j]) <= h.bound) &
            (S::Abs(ncur[j]) <= big);
    W nmth[3], nmdth[3], npend[3 * kMaxDelay];
    const bool sampled = smp[15] != 0;
    if constexpr (!Digital) {
      // the law at t' from the exact state X = (q, q', q'')
      W X[9], Z[9], s[3], kept[3];
      for (int j = 0; j < 3; j++) X[3 * j] = nq[j], X[3 * j + 1] = ndq[j], X[3 * j + 2] = nacc[j];
      for (int i = 0; i < 9; i++) Z[i] = X[i] - smp[i];
      Law<T, 0>(p, h, X, Z, nw, smp, nU, s, kept);
      for (int j = 0; j < 3; j++) ok &= (S::Abs(nw[j]) <= big) & (S::Abs(nU[j]) <= big) & (S::Abs(s[j]) <= big);
    } else if (sampled) {
      // DigitalLoop.update: measure (quantize, differences), the law, delay, saturate
      W Y[9], Z[9], s[3], Ul[3];
      for (int j = 0; j < 3; j++) {
        const W qe = p.q[j];  // fosmc_jax._loop.digital.quantize, with its straight-through form
        const W rounded = qe > 0 ? qe * S::Map(nq[j] / qe, [](T a) { return std::nearbyint(a); }) : nq[j];
        const W th = nq[j] + (rounded - nq[j]);
        W dth = ndq[j], ddth = nacc[j];
        if (h.difference) dth = (th - st[kMemTh + j]) / p.T_, ddth = (dth - st[kMemDth + j]) / p.T_;
        nmth[j] = th, nmdth[j] = dth;
        Y[3 * j] = th, Y[3 * j + 1] = dth, Y[3 * j + 2] = ddth;
      }
      for (int i = 0; i < 9; i++) Z[i] = Y[i] - smp[i];
      Law<T, 1>(p, h, Y, Z, w, smp, Ul, s, nw);
      const W* applied = Ul;
      if (h.delay) {
        for (int i = 0; i < 3 * (h.delay - 1); i++) npend[i] = st[kPending + 3 + i];
        for (int j = 0; j < 3; j++) npend[3 * (h.delay - 1) + j] = Ul[j];
        applied = st + kPending;
      }
      for (int j = 0; j < 3; j++) {
        nU[j] = S::Min(S::Max(applied[j], -p.u_max[j]), p.u_max[j]);
        ok &= (S::Abs(nw[j]) <= big) & (S::Abs(s[j]) <= big) & (S::Abs(nmth[j]) <= big) & (S::Abs(nmdth[j]) <= big) &
              (S::Abs(nU[j]) <= big);
      }
      for (int i = 0; i < 3 * h.delay; i++) ok &= S::Abs(npend[i]) <= big;
    } else {
      for (int j = 0; j < 3; j++) nU[j] = U[j];
    }
    // _simulator._guard: a rollout that diverged, or fails now, keeps its old carry
    const auto diverged = st[kDiv] != 0;
    const auto keep = diverged | ~ok;
    st[kDivAt] = (~diverged & ~ok) ? zero + smp[14] : st[kDivAt];
    st[kDiv] = keep ? zero + 1 : zero;
    for (int j = 0; j < 3; j++) {
      // fosmc_jax._simulator.metrics.add
      W* a = st + kMet + j;  // the field f of joint j: a[3 * f]
      const W e = nq[j] - smp[3 * j], u = nU[j], r = U[j] - a[3 * kULow];
      const W fresh[10] = {a[3 * kCount] + 1,
                           a[3 * kSumE2] + e * e,
                           S::Max(a[3 * kMaxE], S::Abs(e)),
                           e,
                           a[3 * kTV] + S::Abs(u - U[j]),
                           a[3 * kSumU2] + u * u,
                           S::Max(a[3 * kMaxU], S::Abs(u)),
                           U[j] - r * h.decay,
                           a[3 * kSumHf2] + r * r * h.hf_weight,
                           a[3 * kSaturated] + (S::Abs(u) >= p.u_max[j] ? zero + 1 : zero)};
      for (int g = 0; g < 10; g++) a[3 * g] = keep ? a[3 * g] : fresh[g];
    }
    for (int j = 0; j < 3; j++) {
      st[kQ + j] = keep ? st[kQ + j] : nq[j];
      st[kDq + j] = keep ? st[kDq + j] : ndq[j];
      st[kCur + j] = keep ? st[kCur + j] : ncur[j];
      st[kAcc + j] = keep ? st[kAcc + j] : nacc[j];
      st[kU + j] = keep ? st[kU + j] : nU[j];
      if (!Digital || sampled) st[kW + j] = keep ? st[kW + j] : nw[j];
      if (Digital && sampled) {
        st[kMemTh + j] = keep ? st[kMemTh + j] : nmth[j];
        st[kMemDth + j] = keep ? st[kMemDth + j] : nmdth[j];
      }
    }
    if (Digital && sampled)
      for (int i = 0; i < 3 * h.delay; i++) st[kPending + i] = keep ? st[kPending + i] : npend[i];
  }
  for (int64_t r = 0; r < rows; r++) S::Store(out + r * N, st[r]);
}

template <typename T>
ffi::Error Dispatch(ffi::ThreadPool pool, ffi::AnyBuffer lanes, ffi::AnyBuffer consts, ffi::AnyBuffer table,
                    ffi::AnyBuffer in, ffi::Result<ffi::AnyBuffer> out, int32_t rk4, int32_t digital, int32_t kind,
                    int32_t sw, int32_t law, int32_t difference, int32_t delay) {
  // every check the Python side already makes, so that a misuse is an error, never a crash
  const auto type = in.element_type();
  if (lanes.element_type() != type || consts.element_type() != type || table.element_type() != type ||
      out->element_type() != type)
    return ffi::Error::InvalidArgument("fosmc arm kernel: every buffer must have the carry's dtype");
  const auto dims = in.dimensions(), ld = lanes.dimensions(), td = table.dimensions();
  const int64_t stages = digital ? 0 : (rk4 ? 3 : 1);
  if (delay < 0 || delay > kMaxDelay || kind < 0 || kind > 2 || sw < 0 || sw > 3 || law < 0 || law > 1)
    return ffi::Error::InvalidArgument("fosmc arm kernel: switching, law or delay out of range");
  if (dims.size() != 2 || dims[0] != kCarryRows + 3 * delay || ld.size() != 2 || ld[0] != kLaneRows ||
      ld[1] != dims[1] || td.size() != 2 || td[1] != 9 * stages + kSampleCols ||
      out->element_count() != in.element_count() || consts.element_count() != 4)
    return ffi::Error::InvalidArgument("fosmc arm kernel: buffer shapes do not match the layout in arm_kernel.cc");
  const int64_t N = dims[1], L = td[0], R = td[1], rows = dims[0], Wd = Simd<T>::W;
  if (N % Wd) return ffi::Error::InvalidArgument("fosmc arm kernel: the lane count must fill whole blocks");
  const T* c = consts.typed_data<T>();
  const How<T> h{c[0], c[1], c[2], c[3], kind, sw, law, difference, delay};
  const T *lp = lanes.typed_data<T>(), *tb = table.typed_data<T>(), *ip = in.typed_data<T>();
  T* op = out->typed_data<T>();
  auto run = [&](auto block) {
    fosmc::RunBlocks(pool, N / Wd, [=](int64_t i) { block(h, lp + i * Wd, tb, L, R, ip + i * Wd, op + i * Wd, N, rows); });
    return ffi::Error::Success();
  };
  if (digital) return rk4 ? run(Block<T, 1, 1>) : run(Block<T, 0, 1>);
  return rk4 ? run(Block<T, 1, 0>) : run(Block<T, 0, 0>);
}

ffi::Error Advance(ffi::ThreadPool pool, ffi::AnyBuffer lanes, ffi::AnyBuffer consts, ffi::AnyBuffer table,
                   ffi::AnyBuffer in, ffi::Result<ffi::AnyBuffer> out, int32_t rk4, int32_t digital, int32_t kind,
                   int32_t sw, int32_t law, int32_t difference, int32_t delay) {
  switch (in.element_type()) {
    case ffi::DataType::F32:
      return Dispatch<float>(pool, lanes, consts, table, in, out, rk4, digital, kind, sw, law, difference, delay);
    case ffi::DataType::F64:
      return Dispatch<double>(pool, lanes, consts, table, in, out, rk4, digital, kind, sw, law, difference, delay);
    default:
      return ffi::Error::InvalidArgument("fosmc arm kernel: float32 or float64 only");
  }
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(FosmcArmAdvance, Advance,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()  // lanes
                                  .Arg<ffi::AnyBuffer>()  // consts
                                  .Arg<ffi::AnyBuffer>()  // table
                                  .Arg<ffi::AnyBuffer>()  // carry in
                                  .Ret<ffi::AnyBuffer>()  // carry out
                                  .Attr<int32_t>("rk4")
                                  .Attr<int32_t>("digital")
                                  .Attr<int32_t>("kind")
                                  .Attr<int32_t>("switching")
                                  .Attr<int32_t>("law")
                                  .Attr<int32_t>("difference")
                                  .Attr<int32_t>("delay"));
