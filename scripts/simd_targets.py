"""
Print the SIMD dispatch targets numpy found on this CPU, space-separated.

`.ci/run` passes them to NPY_DISABLE_CPU_FEATURES to re-run the tests that read
data made elsewhere under another dispatch (numpy's baseline kernels only).
"""

from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__

print(' '.join(target for target in __cpu_dispatch__ if __cpu_features__.get(target)))
