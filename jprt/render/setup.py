"""Mitsuba set-up: variant selection and the LLVM runtime Dr.Jit's LLVM backend needs.

Dr.Jit 1.5 (Mitsuba 3.9) aborts with "Cannot select: fminimum" when it JIT-compiles through
libLLVM 14 or 15, which is what a bare Debian 12 has. It needs libLLVM >= 16 (Debian package
``libllvm19``), announced through ``DRJIT_LIBLLVM_PATH`` *before* ``drjit`` is imported. This
module finds such a library, sets the variable and selects the variant; it never falls back
silently to the (much slower) scalar variant.

Environment variables:
  JPRT_MITSUBA_VARIANT   Mitsuba variant (default ``llvm_ad_rgb``).
  DRJIT_LIBLLVM_PATH     used as is when it names a libLLVM >= 16.
  JPRT_LLVM_SEARCH_DIRS  ``os.pathsep``-separated folders searched instead of the system ones.
"""

from __future__ import annotations

import glob
import os
import re
import sys

__all__ = [
    "DEFAULT_VARIANT",
    "INSTALL_COMMAND",
    "MIN_LLVM_MAJOR",
    "LLVMNotFoundError",
    "find_libllvm",
    "llvm_major",
    "mitsuba",
    "variant",
]

DEFAULT_VARIANT = "llvm_ad_rgb"
MIN_LLVM_MAJOR = 16
INSTALL_COMMAND = "apt-get update && apt-get install -y libllvm19"

_SYSTEM_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib64",
    "/usr/lib",
    "/usr/local/lib",
    "/usr/lib/llvm-*/lib",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)


class LLVMNotFoundError(RuntimeError):
    """No libLLVM >= 16 was found for an LLVM Mitsuba variant."""


def llvm_major(path: str) -> int | None:
    """Major version of a libLLVM shared library, read from its file name.

    Handles Debian's ``libLLVM-19.so``, ``libLLVM.so.19.1``, ``libLLVM-19.so.1`` and macOS's
    ``libLLVM.dylib`` inside ``llvm-19`` folders. Returns None when no version can be read.
    """
    name = os.path.basename(path)
    m = re.match(r"libLLVM-(\d+)", name) or re.match(r"libLLVM\.so\.(\d+)", name)
    if m is None:
        m = re.search(r"llvm[-@]?(\d+)", path)
    return int(m.group(1)) if m else None


def _search_dirs() -> list[str]:
    custom = os.environ.get("JPRT_LLVM_SEARCH_DIRS")
    patterns = custom.split(os.pathsep) if custom is not None else list(_SYSTEM_DIRS)
    dirs: list[str] = []
    for pattern in patterns:
        dirs.extend(sorted(glob.glob(pattern)))
    return dirs


def find_libllvm(min_major: int = MIN_LLVM_MAJOR) -> str | None:
    """Path of the newest libLLVM shared library with major version >= ``min_major``.

    ``DRJIT_LIBLLVM_PATH`` wins when it names an existing library of a good version.
    """
    preset = os.environ.get("DRJIT_LIBLLVM_PATH")
    if preset and os.path.exists(preset) and (llvm_major(preset) or 0) >= min_major:
        return preset
    found: list[tuple[int, str]] = []
    for folder in _search_dirs():
        for path in glob.glob(os.path.join(folder, "libLLVM*")):
            if not (".so" in path or path.endswith(".dylib")):
                continue
            major = llvm_major(path)
            if major is not None and major >= min_major and os.path.isfile(path):
                found.append((major, path))
    if not found:
        return None
    # Newest version; among its files prefer the shortest name (the unversioned link).
    found.sort(key=lambda mp: (-mp[0], len(mp[1])))
    return found[0][1]


def variant() -> str:
    """The Mitsuba variant jprt uses: ``JPRT_MITSUBA_VARIANT`` or ``llvm_ad_rgb``."""
    return os.environ.get("JPRT_MITSUBA_VARIANT", DEFAULT_VARIANT)


def mitsuba(requested: str | None = None):
    """Import Mitsuba with the jprt variant set, configuring libLLVM first. Returns the module.

    Raises:
      LLVMNotFoundError: an ``llvm_*`` variant is requested and no libLLVM >= 16 exists; the
        message is one line with the exact install command.
    """
    name = requested or variant()
    if name.startswith("llvm"):
        path = find_libllvm()
        if path is None:
            raise LLVMNotFoundError(
                f"Mitsuba variant {name!r} needs libLLVM >= {MIN_LLVM_MAJOR} and none was found; "
                f"install it with: {INSTALL_COMMAND}"
            )
        if "drjit" in sys.modules and os.environ.get("DRJIT_LIBLLVM_PATH") != path:
            # Too late to change the library Dr.Jit loaded; say so rather than crash later.
            current = os.environ.get("DRJIT_LIBLLVM_PATH")
            if current is None or (llvm_major(current) or 0) < MIN_LLVM_MAJOR:
                raise LLVMNotFoundError(
                    "drjit was imported before jprt could set DRJIT_LIBLLVM_PATH; import jprt "
                    f"first or set DRJIT_LIBLLVM_PATH={path}"
                )
        else:
            os.environ["DRJIT_LIBLLVM_PATH"] = path
    import mitsuba as mi

    if mi.variant() != name:
        if name not in mi.variants():
            raise ValueError(f"unknown Mitsuba variant {name!r}; available: {', '.join(mi.variants())}")
        mi.set_variant(name)
    return mi
