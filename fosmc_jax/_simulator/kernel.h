// What the generated kernels' skeleton (gen_kernel.h) builds on: the blocks of rollouts (vecmath.h's
// Simd) spread over XLA's intra-op thread pool.
#pragma once

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <thread>

#include "vecmath.h"  // Simd
#include "xla/ffi/api/ffi.h"

namespace fosmc {

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
