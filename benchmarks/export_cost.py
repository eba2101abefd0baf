"""What one call of the exported controller costs: floating-point operations per
``<name>_update`` (counted) and nanoseconds per call on this CPU, for each controller kind
and precision of ``fosmc export`` on the realistic preset (BENCHMARKS.md, "Issue 26"):

    python benchmarks/export_cost.py            # about 30 s on 2 cores

Counted: the generated C is compiled as C++ with its real type replaced by a class whose
operators and libm overloads count what runs (``+ - * /``, comparisons, sqrt, fabs, sin, cos,
tanh, int -> real conversions), over a 4 s run of the preset's cycloid (4,000 samples, the
encoders a few counts off the reference), and divided by the calls: the operations of the code
as written (the compiler may fold none of them: IEEE arithmetic forbids dropping x * 0).
Timed: the same run compiled as C99 with ``-O2`` (``cc``), ``<name>_update`` alone (the
reference samples precomputed), the best of 7 repeats of 20 x 4,000 calls; and
``<name>_reference_at`` alone.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

PRESET = Path(__file__).resolve().parent.parent / "tuning" / "configs" / "realistic_arm.toml"


#: The counting real type (C++): every arithmetic operator, comparison and libm call tallied.
COUNTER = r"""
#include <cstdint>
#include <cstdio>
#include <math.h>
#define VAL(x) ((x).v)
struct Tally { long add, mul, div, sqrt, cmp, fabs, sin, cos, tanh, conv; };
static Tally tally;
struct R {
    double v;
    R() : v(0) {}
    R(double x) : v(x) {}
    R(int x) : v(x) { tally.conv++; }
    R(unsigned x) : v(x) { tally.conv++; }
    R &operator+=(R b) { tally.add++; v += b.v; return *this; }
    R &operator-=(R b) { tally.add++; v -= b.v; return *this; }
    R &operator*=(R b) { tally.mul++; v *= b.v; return *this; }
    R &operator/=(R b) { tally.div++; v /= b.v; return *this; }
};
inline R operator+(R a, R b) { tally.add++; return R(a.v + b.v); }
inline R operator-(R a, R b) { tally.add++; return R(a.v - b.v); }
inline R operator*(R a, R b) { tally.mul++; return R(a.v * b.v); }
inline R operator/(R a, R b) { tally.div++; return R(a.v / b.v); }
inline R operator-(R a) { return R(-a.v); }  /* a sign flip: no operation counted */
inline bool operator<(R a, R b) { tally.cmp++; return a.v < b.v; }
inline bool operator>(R a, R b) { tally.cmp++; return a.v > b.v; }
inline R sqrt(R a) { tally.sqrt++; return R(std::sqrt(a.v)); }
inline R sqrtf(R a) { return sqrt(a); }
inline R fabs(R a) { tally.fabs++; return R(std::fabs(a.v)); }
inline R fabsf(R a) { return fabs(a); }
inline R sin(R a) { tally.sin++; return R(std::sin(a.v)); }
inline R sinf(R a) { return sin(a); }
inline R cos(R a) { tally.cos++; return R(std::cos(a.v)); }
inline R cosf(R a) { return cos(a); }
inline R tanh(R a) { tally.tanh++; return R(std::tanh(a.v)); }
inline R tanhf(R a) { return tanh(a); }
"""

#: The run both harnesses make: the preset's cycloid, the encoders a few counts off it.
RUN = r"""
#define SAMPLES 4000
static {P}_reference refs[SAMPLES];
static int32_t counts[SAMPLES][3];

static void prepare(void)
{{
    int j, i;
    for (j = 0; j < SAMPLES; j++) {{
        {P}_reference_at((uint32_t)j, &refs[j]);
        for (i = 0; i < 3; i++)
            counts[j][i] = (int32_t)floor(VAL(refs[j].theta[i]) / Q + 0.5) + (j * (i + 1)) % 7 - 3;
    }}
}}

static void start({P}_state *st)
{{
    {P}_real x0[9] = {{0}};
    int i;
    for (i = 0; i < 3; i++)
        x0[3 * i] = refs[0].theta[i];
    {P}_init(st, x0);
}}
"""

COUNT_MAIN = r"""
int main(void)
{{
    {P}_state st;
    {P}_real u[3];
    {P}_reference r;
    double total = 0;
    int j;
    prepare();
    start(&st);
    tally = Tally();
    for (j = 0; j < SAMPLES; j++) {{
        {P}_update(&st, counts[j], &refs[j], u);
        total += u[0].v;
    }}
    Tally update = tally;
    tally = Tally();
    for (j = 0; j < SAMPLES; j++)
        {P}_reference_at((uint32_t)j, &r);
    Tally ref = tally;
    std::printf("%ld %ld %ld %ld %ld %ld %ld %ld %ld %ld\n", update.add, update.mul, update.div, update.sqrt,
                update.cmp, update.fabs, update.sin, update.cos, update.tanh, update.conv);
    std::printf("%ld %ld %ld %ld %ld %ld %ld %ld %ld %ld\n", ref.add, ref.mul, ref.div, ref.sqrt, ref.cmp,
                ref.fabs, ref.sin, ref.cos, ref.tanh, ref.conv);
    return total != total;
}}
"""

TIME_MAIN = r"""
static double now(void)
{{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}}

int main(void)
{{
    {P}_state st;
    {P}_real u[3];
    volatile {P}_real sink = 0;
    double best = 1e30, best_ref = 1e30;
    int rep, k, j;
    prepare();
    for (rep = 0; rep < 7; rep++) {{
        double t0 = now(), t1;
        for (k = 0; k < 20; k++) {{
            start(&st);
            for (j = 0; j < SAMPLES; j++) {{
                {P}_update(&st, counts[j], &refs[j], u);
                sink += u[0];
            }}
        }}
        t1 = now();
        if (t1 - t0 < best)
            best = t1 - t0;
        t0 = now();
        for (k = 0; k < 20; k++)
            for (j = 0; j < SAMPLES; j++) {{
                {P}_reference r;
                {P}_reference_at((uint32_t)j, &r);
                sink += r.theta[0];
            }}
        t1 = now();
        if (t1 - t0 < best_ref)
            best_ref = t1 - t0;
    }}
    printf("%.3f %.3f\n", 1e9 * best / (20.0 * SAMPLES), 1e9 * best_ref / (20.0 * SAMPLES));
    return sink != sink;
}}
"""

FIELDS = ("add", "mul", "div", "sqrt", "cmp", "fabs", "sin", "cos", "tanh", "conv")


def c_compiler() -> str | None:
    """``$CC``, else the first C compiler on the PATH (what ``fosmc export`` checks with)."""
    return next((c for c in (os.environ.get("CC"), "cc", "gcc", "clang") if c and shutil.which(c.split()[0])), None)


def export(kind: str, precision: str, where: Path) -> tuple[Path, float]:
    """``fosmc export`` of the preset with ``kind``, into ``where``; the encoder's q (rad)."""
    toml = PRESET.read_text().replace("[controller]\n", f'[controller]\nkind = "{kind}"\n', 1)
    where.mkdir(parents=True)
    (where / "config.toml").write_text(toml)
    cmd = [sys.executable, "-m", "fosmc_jax", "export", "--config", str(where / "config.toml"), "--out", str(where),
           "--precision", precision]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True)
    counts = 2621440  # the preset's encoder (tuning/configs/realistic_arm.toml)
    assert f"encoders of {counts}, {counts}, {counts}" in (where / "fosmc.h").read_text()
    return where, 2 * np.pi / counts


def count(where: Path, q: float) -> tuple[np.ndarray, np.ndarray]:
    """Operations per update and per reference sample, by :data:`FIELDS`."""
    header = (where / "fosmc.h").read_text()
    real = "typedef double fosmc_real;" if "typedef double" in header else "typedef float fosmc_real;"
    (where / "counted.h").write_text(header.replace(real, "typedef R fosmc_real;"))
    source = (where / "fosmc.c").read_text().replace('#include "fosmc.h"', '#include "counted.h"')
    harness = COUNTER + f"#define Q {q!r}\n" + source + RUN.format(P="fosmc") + COUNT_MAIN.format(P="fosmc")
    (where / "count.cc").write_text(harness)
    cxx = os.environ.get("CXX", "c++")
    subprocess.run([cxx, "-O1", str(where / "count.cc"), "-o", str(where / "count")], check=True)
    lines = subprocess.run([str(where / "count")], check=True, capture_output=True, text=True).stdout.split("\n")
    update, ref = (np.array(line.split(), float) / 4000 for line in lines[:2])
    return update, ref


def time_calls(where: Path, q: float) -> tuple[float, float]:
    """ns per update and per reference sample (best of 7)."""
    head = (
        "#define _POSIX_C_SOURCE 199309L\n#include <math.h>\n#include <stdio.h>\n#include <time.h>\n"
        '#include "fosmc.h"\n#define VAL(x) ((double)(x))\n'
    )
    (where / "timing.c").write_text(head + f"#define Q {q!r}\n" + RUN.format(P="fosmc") + TIME_MAIN.format(P="fosmc"))
    cc = c_compiler()
    subprocess.run([*cc.split(), "-std=c99", "-O2", str(where / "timing.c"), str(where / "fosmc.c"), "-o",
                    str(where / "timing"), "-lm"], check=True)  # fmt: skip
    out = subprocess.run([str(where / "timing")], check=True, capture_output=True, text=True).stdout.split()
    return float(out[0]), float(out[1])


def main() -> None:
    argparse.ArgumentParser(description=__doc__.split("\n\n")[0]).parse_args()
    if c_compiler() is None:
        raise SystemExit("export_cost: no C compiler ($CC, cc, gcc, clang)")
    print(f"load average {os.getloadavg()[0]:.1f}, {os.cpu_count()} cores")
    print(
        "| kind | precision | + - | * | / | sqrt | compare | fabs | tanh | int -> real | flops (+ - * / sqrt) "
        "| ns per update | reference: flops, sin + cos, ns |"
    )
    print("|---|---|" + "---:|" * 11)
    with tempfile.TemporaryDirectory() as tmp:
        for kind in ("fosmc", "smc", "super_twisting"):
            for precision in ("float32", "float64"):
                where, q = export(kind, precision, Path(tmp) / f"{kind}_{precision}")
                n, ref = count(where, q)
                ns, ns_ref = time_calls(where, q)
                c = dict(zip(FIELDS, n))
                flops = c["add"] + c["mul"] + c["div"] + c["sqrt"]
                rflops = ref[0] + ref[1] + ref[2] + ref[3]
                print(f"| {kind} | {precision} | {c['add']:.0f} | {c['mul']:.0f} | {c['div']:.0f} | {c['sqrt']:.0f} "
                      f"| {c['cmp']:.1f} | {c['fabs']:.0f} | {c['tanh']:.0f} | {c['conv']:.0f} | {flops:.0f} | {ns:.0f} "
                      f"| {rflops:.0f}, {ref[6] + ref[7]:.0f}, {ns_ref:.0f} |")  # fmt: skip
    print(f"load average {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
