"""Which of a folder's images are depth, without opening every file of a 100 000-frame folder.

Datasets ship depth beside the images made from it: ``sample3_depth_u16.png`` (the depth) beside
``sample3_depth_u8.png`` (an 8-bit preview), ``sample3_rgb.png`` and ``sample3_label.png``. What a
file is comes from its header (depth_images.kind_of: a PNG's IHDR, a PGM's maxval), read for one
file of each group of names that differ only by their frame number:

- names are first split by shape, their digit runs as one mark (``sample#_depth_u#.png``);
- in a shape of more than READ_EACH files, a digit run taking many values (a frame number, a
  timestamp) stays a mark, one taking at most FEW values (``u16``/``u8``, a camera index) is part
  of the group's name: ``sample#_depth_u16.png`` and ``sample#_depth_u8.png`` are two groups,
  whichever sorts first;
- the first and the last file of each group are read; if they differ, every file of it is;
- a shape of READ_EACH files or fewer has every file read (about 30 us each).

A file of another kind in the middle of a group is then read as its group's kind and refused
when its frame comes, with the ``?glob=`` hint.
"""

from __future__ import annotations

import re
from pathlib import Path

from drivers.formats.depth_images import kind_of

DIGITS = re.compile(r"([0-9]{1,18})")
READ_EACH = 64  # files of one name shape that are each read (64 x ~30 us: 2 ms)
FEW = 16  # distinct values of a digit run that make it part of a group's name, not a frame number


def _groups(names: list[str]) -> list[list[int]]:
    """Indices of ``names`` (one shape, so as many digit runs each) grouped by their digit runs
    that take at most FEW values, in the order the names came."""
    runs = [DIGITS.findall(name) for name in names]
    kept = [k for k in range(len(runs[0])) if len({r[k] for r in runs}) <= FEW]
    groups: dict[tuple[str, ...], list[int]] = {}
    for i, r in enumerate(runs):
        groups.setdefault(tuple(r[k] for k in kept), []).append(i)
    return list(groups.values())


def image_kinds(paths: list[Path]) -> list[tuple[Path, str]]:
    """Each image with its kind ("depth", "colour", "8-bit" or "unknown", as
    depth_images.kind_of says), in the order given, reading as few headers as the names allow."""
    shapes: dict[str, list[int]] = {}
    for i, path in enumerate(paths):
        shapes.setdefault(DIGITS.sub("#", path.name), []).append(i)
    kinds = [""] * len(paths)
    for members in shapes.values():
        if len(members) <= READ_EACH:
            for i in members:
                kinds[i] = kind_of(paths[i])
            continue
        for group in _groups([paths[i].name for i in members]):
            first, last = members[group[0]], members[group[-1]]
            kind = kind_of(paths[first])
            if kind_of(paths[last]) != kind:  # mixed under one name: each file says
                for j in group:
                    kinds[members[j]] = kind_of(paths[members[j]])
                continue
            for j in group:
                kinds[members[j]] = kind
    return list(zip(paths, kinds, strict=True))
