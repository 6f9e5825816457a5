"""mapserver.tree.walk: every entry of an uploaded tree, however deep, never through a link,
and the folders it cannot list reported, not dropped."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from mapserver import tree
from mapserver.inbox import check_entry, fingerprint


def test_walk_lists_a_tree_deeper_than_the_recursion_limit(tmp_path: Path) -> None:
    """Python 3.11's os.walk raises RecursionError on 1100 nested folders (session 44's review:
    an rsync upload of such a tree stopped the daemon); the walk lists them all. The depth is
    fixed and the limit set here: the daemon raises the process's limit (Service.run, for
    watchdog's walk), and a depth taken from it made paths longer than PATH_MAX (CI, session 44)."""
    depth = 1100
    cur = str(tmp_path / "top")
    os.mkdir(cur)
    for _ in range(depth):
        cur += "/a"
        os.mkdir(cur)
    Path(cur, "file").write_text("x")
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(1000)  # Python's default, below the depth
    try:
        found = list(tree.walk(tmp_path / "top"))
    finally:
        sys.setrecursionlimit(limit)
    assert len(found) == depth + 1
    assert found[-1].endswith("/a/file")
    assert fingerprint(tmp_path / "top") is not None
    # Removed here, deepest first: pytest's own clean-up of old temporary folders (shutil.rmtree)
    # recurses, and a later run would fail on this tree.
    os.unlink(os.path.join(cur, "file"))
    while cur != str(tmp_path):
        os.rmdir(cur)
        cur = os.path.dirname(cur)


def test_walk_does_not_follow_links_and_reports_a_folder_it_cannot_list(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "b" / "inner").mkdir(parents=True)
    (tmp_path / "b" / "inner" / "f").write_text("x")
    (tmp_path / "b" / "link").symlink_to("inner")
    assert sorted(os.path.relpath(p, tmp_path / "b") for p in tree.walk(tmp_path / "b")) == [
        "inner",
        os.path.join("inner", "f"),
        "link",
    ]
    # A folder the daemon may not list (a robot's sub-folder of mode 0700 as another user:
    # root reads anything, so os.scandir is made to refuse it here).
    real = os.scandir
    locked = str(tmp_path / "b" / "inner")

    def scandir(path: str) -> object:
        if os.fspath(path) == locked:
            raise PermissionError(13, "Permission denied", locked)
        return real(path)

    monkeypatch.setattr(os, "scandir", scandir)
    errors: list[str] = []
    assert "inner/f" not in " ".join(tree.walk(tmp_path / "b", lambda p, e: errors.append(p)))
    assert errors == [locked]
    # The fingerprint keeps it (type -1, the errno), and the check names it: the bundle is
    # failed with a reason, the daemon goes on (it used to raise out of the main loop).
    print_ = fingerprint(tmp_path / "b")
    assert print_ is not None and ("inner/", -1, 13, 0, 0, 0) in print_
    (tmp_path / "b" / "bundle.yaml").write_text("format: 1\n")
    with pytest.raises(Exception, match="cannot read this folder of the bundle"):
        check_entry(tmp_path / "b")
