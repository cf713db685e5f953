"""The PIL target image: the cross toolchain, the emulator, and the ELF built from the C sources.

Owns what ``--firmware pil`` needs on the machine (:data:`APT_PACKAGES`, :func:`missing_tools`,
:func:`require_tools`: one line naming the option and the apt packages, exit 2) and the target
image (:func:`build_image`): ``arm-none-eabi-gcc`` compiles the drive's control period
(``firmware_model/c/ilc_control.c``, the same source the host build uses) with the target's
startup, UART driver and protocol loop (``firmware_model/c/pil/``) for the Cortex-M4F of QEMU's
``mps2-an386``.  The ELF is cached under :func:`cache_dir` in a folder named by a hash of the
sources, the flags and the compiler's version, written atomically (:mod:`bus.atomic`) under a
file lock, so the four drive processes of a rig that start at once build it once.

May import: bus (and the standard library).
"""

from __future__ import annotations

import fcntl
import functools
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from bus.atomic import atomic_path
from bus.errors import IlcrigError, InputError

logger = logging.getLogger(__name__)

__all__ = [
    "APT_PACKAGES",
    "CFLAGS",
    "GCC",
    "QEMU",
    "PilBuildError",
    "build_image",
    "cache_dir",
    "missing_tools",
    "require_tools",
]

#: the cross compiler and the emulator (Debian: gcc-arm-none-eabi, qemu-system-arm)
GCC = "arm-none-eabi-gcc"
QEMU = "qemu-system-arm"
#: what ``apt-get install`` needs for ``--firmware pil`` (libnewlib-arm-none-eabi: the
#: toolchain's libgcc multilibs and headers come with it on Debian)
APT_PACKAGES = ("gcc-arm-none-eabi", "libnewlib-arm-none-eabi", "qemu-system-arm")
#: where the ELF is cached (default: $XDG_CACHE_HOME or ~/.cache, then ilcrig/pil)
CACHE_ENV = "ILCRIG_PIL_CACHE"

_C_DIR = Path(__file__).resolve().parent / "c"
_PIL_DIR = _C_DIR / "pil"
#: the sources of the image, in link order (the drive's control period is fwc's ilc_control.c)
SOURCES: tuple[Path, ...] = (
    _PIL_DIR / "startup.c",
    _PIL_DIR / "uart.c",
    _PIL_DIR / "pil_main.c",
    _C_DIR / "ilc_control.c",
)
HEADERS: tuple[Path, ...] = (
    _C_DIR / "ilc_drive.h",
    _PIL_DIR / "pil_protocol.h",
    _PIL_DIR / "pil_target.h",
)
LINKER_SCRIPT = _PIL_DIR / "pil.ld"
#: Cortex-M4F (hard-float ABI, the M4's single-precision FPU: gcc moves 64-bit values through
#: its registers), -O2 as firmware is built; freestanding, no libc (libgcc for helpers)
CFLAGS: tuple[str, ...] = (
    "-std=c99",
    "-Wall",
    "-Wextra",
    "-Werror",
    "-O2",
    "-mcpu=cortex-m4",
    "-mthumb",
    "-mfloat-abi=hard",
    "-mfpu=fpv4-sp-d16",
    "-ffreestanding",
    "-fno-tree-loop-distribute-patterns",  # memcpy/memset of startup.c must not call themselves
    "-ffunction-sections",
    "-fdata-sections",
    "-nostdlib",
    "-Wl,--gc-sections",
)
IMAGE_NAME = "ilc_pil.elf"
_BUILD_TIMEOUT_S = 120.0


class PilBuildError(IlcrigError):
    """The target image could not be built (the compiler's message says why)."""


def missing_tools() -> list[str]:
    """The programs of ``--firmware pil`` not found on PATH (empty: all there)."""
    return [tool for tool in (GCC, QEMU) if shutil.which(tool) is None]


def require_tools(option: str = "--firmware") -> None:
    """Raise :class:`bus.errors.InputError` (one line, exit 2) naming ``option`` and the apt
    packages when the cross compiler or QEMU is missing -- called before any process starts."""
    missing = missing_tools()
    if missing:
        raise InputError(
            f"{option}: pil needs {' and '.join(missing)} on PATH (processor in the loop): "
            f"apt-get install {' '.join(APT_PACKAGES)}"
        )


def cache_dir() -> Path:
    """The folder of cached images: $ILCRIG_PIL_CACHE, else $XDG_CACHE_HOME/ilcrig/pil, else
    ~/.cache/ilcrig/pil."""
    explicit = os.environ.get(CACHE_ENV)
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "ilcrig" / "pil"


@functools.cache
def _compiler_version() -> str:
    out = subprocess.run([GCC, "--version"], capture_output=True, text=True, check=False, timeout=_BUILD_TIMEOUT_S)
    return out.stdout.splitlines()[0] if out.stdout else ""


def image_key() -> str:
    """The hash naming an image: sources, headers, linker script, flags, compiler version."""
    h = hashlib.sha256()
    for path in (*SOURCES, *HEADERS, LINKER_SCRIPT):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    h.update("\0".join(CFLAGS).encode())
    h.update(_compiler_version().encode())
    return h.hexdigest()[:16]


def build_image(root: Path | None = None) -> Path:
    """The target ELF, built now unless cached (see the module docstring).

    :param root: the cache folder (default :func:`cache_dir`)
    :raises InputError: the toolchain or QEMU is missing
    :raises PilBuildError: the compiler failed
    """
    require_tools()
    folder = (cache_dir() if root is None else root) / image_key()
    elf = folder / IMAGE_NAME
    if elf.is_file():
        return elf
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "build.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # another drive process may be building it now
        if elf.is_file():
            return elf
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            out = Path(tmp) / IMAGE_NAME
            argv = [
                GCC,
                *CFLAGS,
                f"-I{_C_DIR}",
                "-T",
                str(LINKER_SCRIPT),
                *(str(s) for s in SOURCES),
                "-lgcc",
                "-o",
                str(out),
            ]
            logger.info("building the PIL image: %s", " ".join(argv))
            done = subprocess.run(argv, capture_output=True, text=True, check=False, timeout=_BUILD_TIMEOUT_S)
            if done.returncode != 0:
                raise PilBuildError(f"{GCC} failed ({done.returncode}): {done.stderr.strip()}")
            with atomic_path(elf) as target:
                shutil.copyfile(out, target)
    return elf
