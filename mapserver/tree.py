"""Walking a bundle's folder tree without recursion and without following symbolic links.

Python 3.11's ``os.walk`` recurses, so an upload nested a thousand folders deep raises
``RecursionError``; and it drops the folders it cannot list without a word. Every walk of an
uploaded tree (the inbox's fingerprint and checks, the outbox's duplicate check) goes through
:func:`walk`, which does neither (``os.walk`` does the same listing on 3.12 and later, without
the recursion; this keeps one behaviour on every supported Python).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator


def walk(
    root: str | os.PathLike[str], on_error: Callable[[str, OSError], None] | None = None
) -> Iterator[str]:
    """The path of everything under ``root`` (not ``root`` itself), each folder's entries after
    the folder, never through a symbolic link. A folder that cannot be listed is passed to
    ``on_error`` (path, error) and skipped."""
    stack = [os.fspath(root)]
    while stack:
        folder = stack.pop()
        try:
            with os.scandir(folder) as entries:
                listed = list(entries)
        except OSError as error:
            if on_error is not None:
                on_error(folder, error)
            continue
        subfolders = []
        for entry in listed:
            yield entry.path
            try:
                if entry.is_dir(follow_symlinks=False):
                    subfolders.append(entry.path)
            except OSError:
                pass  # gone, or unreadable: its lstat says so to whoever asks
        stack.extend(reversed(subfolders))
