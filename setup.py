"""Build of deepcontact's one compiled module; everything else is in pyproject.toml.

deepcontact/_transfer.c is the inner loop of the particle/grid transfer
(deepcontact.transfer). `pip install -e .` (run by `make setup`) builds it in
place. -ffp-contract=off: no fused multiply-adds, so the kernel weights are
the same numbers on every x86-64 machine, whatever the compiler's defaults.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "deepcontact._transfer",
            ["deepcontact/_transfer.c"],
            extra_compile_args=["-O3", "-ffp-contract=off", "-fno-math-errno", "-Wall"],
        )
    ]
)
