"""Numbers as people read them in a terminal or a picture: 1.2 MiB/s, 30 Hz, 45%, 1.5 ms.

Short (at most 9 characters or so) so that columns stay narrow; None (not known yet) is "-".
"""
from __future__ import annotations

_BINARY = ("B", "KiB", "MiB", "GiB", "TiB", "PiB")


def size(value: float | None) -> str:
    """Bytes with a binary prefix: 512 B, 1.5 KiB, 20 MiB."""
    if value is None:
        return "-"
    for unit in _BINARY:
        if abs(value) < 1024 or unit == _BINARY[-1]:
            break
        value /= 1024
    return f"{value:.0f} {unit}" if unit == "B" or abs(value) >= 100 else f"{value:.1f} {unit}"


def bandwidth(value: float | None) -> str:
    """Bytes per second: 1.5 MiB/s."""
    return "-" if value is None else f"{size(value)}/s"


def rate(value: float | None) -> str:
    """Events per second as a frequency: 0.5 Hz, 30 Hz, 1.2 kHz."""
    if value is None:
        return "-"
    if abs(value) >= 1000:
        return f"{value / 1000:.1f} kHz"
    return f"{value:.1f} Hz" if abs(value) < 100 else f"{value:.0f} Hz"


def percent(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}%" if abs(value) >= 10 else f"{value:.1f}%"


def duration(seconds: float | None) -> str:
    """A short time: 850 us, 1.5 ms, 2.0 s."""
    if seconds is None:
        return "-"
    if abs(seconds) < 1e-3:
        return f"{seconds * 1e6:.0f} us"
    if abs(seconds) < 1:
        return f"{seconds * 1e3:.1f} ms"
    return f"{seconds:.1f} s"
