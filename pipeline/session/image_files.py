"""Still images read beside the videos (a session's backgrounds, a calibration's board
images): one cut short is named before it is decoded.

OpenCV decodes the part of a cut PNG or JPEG it has (the rest grey), with only libpng's or
libjpeg's own line on stderr.
"""

from __future__ import annotations

# The last chunk of a whole PNG (IEND) and the end-of-image marker of a JPEG: a file cut
# short lacks them. They are sought anywhere in the file, not only at its end: a phone's
# trailer after them (a motion photo's video, megabytes long) is no cut. In a JPEG's coded
# data 0xFF is always followed by 0x00 or a restart marker, so its end marker appears only
# at an end (a cut file whose EXIF thumbnail carries its own goes unnoticed).
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
_JPEG_END = b"\xff\xd9"


def cut_short(data: bytes, suffix: str) -> bool:
    """Whether the bytes ``data`` of an image file named ``...suffix`` (".png", ".JPG", ...)
    are a PNG or JPEG that lacks its end."""
    suffix = suffix.lower()
    if suffix == ".png" and data.startswith(b"\x89PNG"):
        return _PNG_END not in data
    if suffix in (".jpg", ".jpeg") and data.startswith(b"\xff\xd8"):
        return data.find(_JPEG_END, 2) < 0
    return False
