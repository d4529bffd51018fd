"""Build of deepcontact's compiled modules; everything else is in pyproject.toml.

deepcontact/_transfer.c is the inner loop of the particle/grid transfer
(deepcontact.transfer); deepcontact/_kinematics.c the contact points' velocities
and effective masses (deepcontact.kinematics); deepcontact/_admission.c the
admission into the friction cones, its rounds and their factorization
(deepcontact.admission); deepcontact/_faces.c a face's linear system and its dual
solve (deepcontact.faces); the last two share deepcontact/sparse_cholesky.h, a sparse
Cholesky factorization and the orders that keep its factors sparse; deepcontact/_route.c
runs the face route after its classifier in one call (deepcontact.faces.route_compiled) on
the same kernels (the headers deepcontact/*.h, one implementation each). `pip install -e .` (run by `make setup`) builds them in
place. -ffp-contract=off: no fused multiply-adds, so the kernel weights and the
point features are the same numbers on every x86-64 machine, whatever the
compiler's defaults, and the features NumPy's to the bit.
"""

from setuptools import Extension, setup

FLAGS = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-Wall"]
#: The kernels the modules share (static functions, one implementation each).
HEADERS = ("sparse_cholesky", "contact_records", "contact_jacobian", "face_kernels", "admission_kernels")

setup(
    ext_modules=[
        Extension(f"deepcontact.{name}", [f"deepcontact/{name}.c"], extra_compile_args=FLAGS,
                  depends=[f"deepcontact/{h}.h" for h in HEADERS])
        for name in ("_transfer", "_kinematics", "_admission", "_faces", "_route")
    ]
)
