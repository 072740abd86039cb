"""Where the native sensor libraries (libOpenNI2, libfreenect) are looked for: Debian's multiarch
folders first, then the plain and local ones."""

from __future__ import annotations

NATIVE_LIB_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib/arm-linux-gnueabihf",
    "/usr/lib",
    "/usr/local/lib",
)
