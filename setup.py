"""Build of the optional C extensions: ``bus.transports.hub._hubcore`` (the hub's data plane) and
``firmware_model._fwcore`` (the drive firmware's C core, firmware_model/c/, for ``--firmware c``).

Everything else is configured in pyproject.toml. Both extensions are optional: without a C compiler
the install still succeeds; the hub then uses its pure-Python path (the same behaviour, slower) and
only the Python firmware is there (``--firmware c`` says so, exit 2).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "bus.transports.hub._hubcore",
            sources=["bus/transports/hub/_hubcore.c"],
            extra_compile_args=[
                "-O2",
                "-std=c11",
                "-D_GNU_SOURCE",
                "-Wall",
                "-Wextra",
                "-Wno-unused-parameter",
                "-Wno-missing-field-initializers",
                "-Wno-cast-function-type",
            ],
            optional=True,
        ),
        Extension(
            "firmware_model._fwcore",
            sources=["firmware_model/_fwcore.c", "firmware_model/c/ilc_control.c"],
            depends=["firmware_model/c/ilc_drive.h"],
            include_dirs=["firmware_model"],
            extra_compile_args=["-O2", "-std=c99", "-Wall", "-Wextra", "-Wno-cast-function-type"],
            optional=True,
        ),
    ]
)
