"""MIRRORS: second implementations of :mod:`controller.rollout` that must stay copies (of
its math-library build, :data:`controller.rollout.EXACT`).

Everything else in the project has one implementation per equation; these two cannot:

* ``casadi_rollout.py`` - the policy and the MF prediction as a CasADi SX graph, so that
  IPOPT (:mod:`controller.ipopt`) gets exact first and second derivatives. Pinned by
  ``tests/test_ipopt.py`` (symbolic rollout = numba rollout to 1e-9 relative on states that
  drive every clip of the policy; symbolic cost = ``batch_cost`` to 1e-9). The cost is no
  copy: :mod:`controller.cost_terms`' functions, called on the symbols
  (``tests/test_cost_terms.py``).
* ``rollout_ref.c`` - a single-thread C99 reference of the MF batch rollout, the
  throughput the hardware allows (``benchmarks/rollout_bench.py``). Its array indices come
  from a header generated from :mod:`plant.layout` when it is built
  (:func:`plant.layout.c_header`). Pinned by ``tests/test_rollout_ref.py`` (strict IEEE
  build = numba to 1e-9 of each quantity's scale, 1-3 axles).

A change to :mod:`controller.rollout` or :mod:`plant.tire` that these files do not follow
fails those tests; change them together.
"""

from pathlib import Path

C_REFERENCE = Path(__file__).with_name("rollout_ref.c")
