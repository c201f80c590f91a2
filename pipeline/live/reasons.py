"""Why a camera's source stopped, worded for the person at the rig.

FFmpeg's errors (through PyAV) read ``[Errno 1414092869] Immediate exit requested:
'udp://...'``: a number that is FFmpeg's own tag, a text about FFmpeg's internals
rather than the camera, and the source's URL again. A live run names the camera and
its source itself; these functions give what went wrong, and what to check.
"""

from __future__ import annotations

import errno
import socket
from urllib.parse import urlsplit

import av

_PLUGGED_IN = "check that the camera is plugged in"
_PERMISSION = "check that this user may read the device (the video group)"
# (what went wrong, what to check) by the error number FFmpeg or the system gives.
REASONS_BY_ERRNO = {
    errno.ECONNREFUSED: (
        "connection refused",
        "check that the camera, or the program serving its stream, runs at this address",
    ),
    errno.ENOENT: ("no such device or file", f"{_PLUGGED_IN}, and the path in [live]"),
    errno.ENODEV: ("no such device", _PLUGGED_IN),
    errno.ENXIO: ("no such device", _PLUGGED_IN),
    errno.EACCES: ("permission denied", _PERMISSION),
    errno.EPERM: ("permission denied", _PERMISSION),
    errno.EBUSY: ("the device is busy", "close the other program that uses the camera"),
    errno.EHOSTUNREACH: ("host unreachable", "check the network and the URL's host"),
    errno.ENETUNREACH: ("network unreachable", "check the network and the URL's host"),
    errno.ECONNRESET: ("the connection was reset", "check the program serving the camera's stream"),
    errno.EIO: ("input/output error", "check the camera's cable and power"),
}


def ffmpeg_text(exc: BaseException) -> str:
    """The error's own text on one line: an OSError's (FFmpeg's too) ``strerror``, without
    the error number and the source's URL that ``str`` adds to it."""
    text = " ".join(str(getattr(exc, "strerror", None) or exc).split())
    return text[:200] or type(exc).__name__


def outage_reason(
    exc: BaseException, *, opened: bool, open_timeout_s: float, stall_s: float
) -> tuple[str, str]:
    """Why a camera's source failed, and what to check ("" where its text says it).

    ``opened``: the source had opened (the error came while reading it), so a timeout is
    a stall rather than a stream that never came.
    """
    if isinstance(exc, av.error.ExitError):  # its open or read was cut off by the run's timeout
        if opened:
            return f"no frame for {stall_s:g} s", "check the camera's cable, power or stream"
        return (
            f"no stream within {open_timeout_s:g} s",
            "check that the camera sends its stream to this address",
        )
    if isinstance(exc, av.error.InvalidDataError):
        return "FFmpeg cannot read the stream (invalid data)", "check the format the camera sends"
    code = abs(getattr(exc, "errno", None) or 0)  # the system's number, of either sign
    if code in REASONS_BY_ERRNO:
        return REASONS_BY_ERRNO[code]
    if not code:  # neither FFmpeg's error nor the system's: its text says it
        return ffmpeg_text(exc), ""
    return f"FFmpeg: {ffmpeg_text(exc)}", "check the camera's source in [live] and that the camera is on"


def unresolved_host(url: str) -> str:
    """The host name of the network source ``url`` where the system cannot resolve it ("" for
    a device, a file, an address, or a name that resolves): FFmpeg reports that as an
    input/output error, as it does a camera's failing cable."""
    try:
        host = urlsplit(url).hostname
    except ValueError:
        return ""
    if not host or "://" not in url:
        return ""
    try:
        socket.getaddrinfo(host, None)
    except (socket.gaierror, UnicodeError):
        return host
    return ""
