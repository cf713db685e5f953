"""Build of the optional C extension ``bus.transports.hub._hubcore`` (the hub's data plane).

Everything else is configured in pyproject.toml. The extension is optional: without a C compiler
the install still succeeds and the hub uses its pure-Python path (the same behaviour, slower).
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
        )
    ]
)
