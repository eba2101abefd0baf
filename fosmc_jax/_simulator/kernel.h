// What the generated kernels' skeleton (gen_kernel.h) builds on: a block of rollouts as one SIMD
// vector, and the blocks spread over XLA's intra-op thread pool.
#pragma once

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <thread>

#include "xla/ffi/api/ffi.h"

namespace fosmc {

// One block: the CPU's SIMD register (AVX-512: 64 bytes, 8 double or 16 float rollouts; AVX: 32;
// else 16). A block wider than the register takes two registers per value, and the long
// straight-line step then spills what it cannot hold (BENCHMARKS.md, "Issue 32").
// -DFOSMC_SIMD_BYTES=N sets another width (an ablation: FOSMC_JAX_KERNEL_FLAGS).
#if defined(FOSMC_SIMD_BYTES)
constexpr int kBytes = FOSMC_SIMD_BYTES;
#elif defined(__AVX512F__)
constexpr int kBytes = 64;
#elif defined(__AVX__)
constexpr int kBytes = 32;
#else
constexpr int kBytes = 16;
#endif

// A block's rollouts as one GCC vector: each variable below holds one quantity of every
// rollout of the block, each operator acts lane by lane, and a comparison gives a lane mask.
template <typename T>
struct Simd {
  typedef T V __attribute__((vector_size(kBytes)));
  static constexpr int W = kBytes / sizeof(T);
  static V Load(const T* p) { V v; std::memcpy(&v, p, sizeof v); return v; }
  static void Store(T* p, V v) { std::memcpy(p, &v, sizeof v); }
  template <typename F>
  static V Map(V x, F f) {
    V r;
    for (int l = 0; l < W; l++) r[l] = f(x[l]);
    return r;
  }
  static V Abs(V x) { return Map(x, [](T a) { return std::fabs(a); }); }
  static V Sqrt(V x) { return Map(x, [](T a) { return std::sqrt(a); }); }
  static V Max(V a, V b) { return a < b ? b : a; }  // jnp.maximum on finite values (NaN in a stays)
  static V Min(V a, V b) { return b < a ? b : a; }
};

inline std::atomic<int64_t> g_busy{0};  // threads running blocks, over every call in the process

// one(i) for every block i < blocks, on the calling thread and the pool's. Blocks are handed out
// from a shared counter: the calling thread takes its share too and waits only for blocks
// already taken, so the call finishes even if no pool thread is free. A helper that starts when
// every pool thread is already at work in some call (several devices running their shards at
// once) leaves at once instead of oversubscribing the cores. ``one`` is copied into the helpers
// (a helper may outlive the call; it then takes no block): it must capture by value.
template <typename F>
void RunBlocks(xla::ffi::ThreadPool& pool, int64_t blocks, F one) {
  struct Shared {
    std::atomic<int64_t> next{0}, done{0};
  };
  auto shared = std::make_shared<Shared>();
  auto work = [shared, one, blocks] {
    for (int64_t i; (i = shared->next.fetch_add(1)) < blocks;) {
      one(i);
      shared->done.fetch_add(1, std::memory_order_release);
    }
  };
  const int64_t threads = pool.num_threads(), helpers = std::min(threads, blocks) - 1;
  for (int64_t h = 0; h < helpers; h++)
    pool.Schedule([work, threads] {
      if (g_busy.fetch_add(1) < threads) work();
      g_busy.fetch_sub(1);
    });
  g_busy.fetch_add(1);
  work();
  g_busy.fetch_sub(1);
  while (shared->done.load(std::memory_order_acquire) < blocks) std::this_thread::yield();
}

}  // namespace fosmc
