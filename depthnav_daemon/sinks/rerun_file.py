"""Writing ``.rrd`` files for the rerun sink: a file cut short by a full disk is trimmed back to its
last whole message, so everything written before stays readable."""

from __future__ import annotations

import logging
import os
import struct

log = logging.getLogger(__name__)

RRD_MAGIC = b"RRF2"
RRD_FILE_HEADER = 12  # magic, version, options
RRD_MESSAGE_HEADER = struct.Struct("<QQ")  # message kind, payload length
MAX_MESSAGE_KIND = 255  # a larger "kind" is not a message header


def trim_partial_message(path: str) -> int | None:
    """Cut an ``.rrd`` whose writing stopped mid-message (disk full) back to its last whole message.

    rerun's reader refuses a file whose last message is cut short, which would make every frame
    written before the disk filled unreadable. The result has no footer, which rerun reads
    (``RrdReader.stream()``, the viewer). Nothing is changed unless the file walks cleanly.

    Returns:
        The new size in bytes, or None when the file was left as it was.
    """
    try:
        with open(path, "r+b") as fh:
            size = os.fstat(fh.fileno()).st_size
            if fh.read(4) != RRD_MAGIC:
                return None
            pos = RRD_FILE_HEADER
            while pos + RRD_MESSAGE_HEADER.size <= size:
                fh.seek(pos)
                kind, length = RRD_MESSAGE_HEADER.unpack(fh.read(RRD_MESSAGE_HEADER.size))
                if (
                    kind > MAX_MESSAGE_KIND
                ):  # not a message header: an unknown layout, leave the file alone
                    return None
                if pos + RRD_MESSAGE_HEADER.size + length > size:
                    break
                pos += RRD_MESSAGE_HEADER.size + length
            if pos == size:
                return None
            fh.truncate(pos)
            return pos
    except OSError as exc:
        log.warning("rerun sink: could not trim %s: %s", path, exc.strerror or exc)
        return None
