"""Blocking waits on a 32-bit word in shared memory (Linux futex), without spinning.

A futex is the kernel primitive under every pthread mutex and condition
variable; the word lives in the shared mapping, so a producer written in C,
Rust or C++ wakes Python consumers with the same two system calls
(``FUTEX_WAIT`` / ``FUTEX_WAKE`` without the PRIVATE flag, which is what makes
them work across processes). Where no futex is available we fall back to short
sleeps: slower to wake, still no busy loop.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import mmap
import platform
import sys
import time
from collections.abc import Callable

# Syscall numbers differ per architecture; these are the ones Docker hosts run.
_SYS_FUTEX = {"x86_64": 202, "aarch64": 98, "arm64": 98, "riscv64": 98}.get(platform.machine())
_FUTEX_WAIT = 0
_FUTEX_WAKE = 1
_WAKE_ALL = 2**31 - 1
_FALLBACK_POLL_S = 0.0005


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _load_syscall() -> Callable[..., int] | None:
    if not sys.platform.startswith("linux") or _SYS_FUTEX is None:
        return None
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
    fn = libc.syscall
    fn.restype = ctypes.c_long
    syscall: Callable[..., int] = fn
    return syscall


_syscall = _load_syscall()


class FutexWord:
    """One aligned uint32 in a writable mmap, usable as a futex.

    ``release()`` must be called before the mmap is closed: the ctypes view
    pins the buffer.
    """

    def __init__(self, buffer: mmap.mmap, offset: int) -> None:
        if offset % 4:
            raise ValueError(f"futex word must be 4-byte aligned, offset {offset}")
        self._cell: ctypes.c_uint32 | None = ctypes.c_uint32.from_buffer(buffer, offset)
        self._address = ctypes.addressof(self._cell)

    @property
    def value(self) -> int:
        assert self._cell is not None, "futex word used after release()"
        return int(self._cell.value)

    def increment(self) -> None:
        """Bump the word (callers hold the ring lock, so no atomic RMW is needed)."""
        assert self._cell is not None, "futex word used after release()"
        self._cell.value = (self._cell.value + 1) & 0xFFFFFFFF

    def wait(self, expected: int, timeout_s: float) -> bool:
        """Sleep while the word equals ``expected``, at most ``timeout_s``.

        Returns False on timeout, True when woken or when the word already
        differs (the caller re-checks its condition either way).
        """
        if timeout_s <= 0:
            return self.value != expected
        if _syscall is None:
            deadline = time.monotonic() + timeout_s
            while self.value == expected:
                if time.monotonic() >= deadline:
                    return False
                time.sleep(_FALLBACK_POLL_S)
            return True
        sec = int(timeout_s)
        ts = _Timespec(sec, int((timeout_s - sec) * 1e9))
        res = _syscall(
            _SYS_FUTEX,
            ctypes.c_void_p(self._address),
            _FUTEX_WAIT,
            ctypes.c_uint32(expected),
            ctypes.byref(ts),
            None,
            0,
        )
        if res == 0:
            return True
        err = ctypes.get_errno()
        if err == errno.ETIMEDOUT:
            return False
        # EAGAIN: value already changed; EINTR: a signal. Both mean "look again".
        return True

    def wake_all(self) -> None:
        if _syscall is not None:
            _syscall(
                _SYS_FUTEX, ctypes.c_void_p(self._address), _FUTEX_WAKE, _WAKE_ALL, None, None, 0
            )

    def release(self) -> None:
        self._cell = None
