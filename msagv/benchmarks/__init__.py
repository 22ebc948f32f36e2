"""``msagv bench``: the benchmarks' sections (docs/PERFORMANCE.md)."""

# The wear term of the controller the benchmarks time and compare with IPOPT and acados:
# the paper's TWO, as docs/PERFORMANCE.md measured it. The product's default is the wear
# energy (controller.models.MPCSettings.method); a candidate costs the same under either.
BENCH_METHOD = "two"
