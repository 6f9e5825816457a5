"""A small cache of decoded global maps, keyed by content.

Every bundle carries (or names) the global map, and in a fleet it is nearly always the same map:
decoding it again for each bundle costs more than the rest of the pipeline on large PNG maps.
The key is the content (the YAML's bytes and the image's sha256, taken from the manifest's
checksums when the completeness check has already verified them), so a changed map is never
served stale, whatever its path. An image's hash
is remembered by path, size and modification time (a rewritten file is hashed again).

The cached arrays are made read-only: the pipeline's stages are pure functions and must not
write to them.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from dataclasses import replace
from pathlib import Path

from mapserver.bundle import sha256_file
from mapserver.errors import MapFileError
from mapserver.maps import OccupancyMap, load_map

# How many image digests a cache remembers (a few per map in use: the bundles' copies).
_DIGESTS_KEPT = 16


class MapCache:
    """Least-recently-used cache of :class:`OccupancyMap` by content; ``capacity`` maps."""

    def __init__(self, capacity: int = 2) -> None:
        if capacity < 0:
            raise ValueError(f"capacity must be >= 0, got {capacity}")
        self.capacity = capacity
        self.hits = 0
        self.misses = 0
        self._maps: OrderedDict[tuple[str, str], OccupancyMap] = OrderedDict()
        self._digests: OrderedDict[tuple[str, int, int], str] = OrderedDict()
        self._lock = threading.Lock()

    def digest(self, image_path: Path, known: str | None = None) -> str:
        """The sha256 of an image: ``known`` when given (already verified), else remembered by
        path, size and mtime (the maps a worker sees are hashed once, for the cache's key and
        for whoever asks again: the fleet map's lookup)."""
        if known:
            return known.lower()
        try:
            st = Path(image_path).stat()
            key = (str(image_path), st.st_size, st.st_mtime_ns)
            with self._lock:
                found = self._digests.get(key)
            if found is not None:
                return found
            found = sha256_file(image_path)
        except OSError as error:
            # An image the daemon may not read (another user's mode 0600 file): the bundle's
            # fault, said so, not "failed unexpectedly, please report" (session 44's review).
            raise MapFileError(
                f"cannot read image: {error.strerror or error}", file=image_path
            ) from None
        with self._lock:
            self._digests[key] = found
            while len(self._digests) > _DIGESTS_KEPT:
                self._digests.popitem(last=False)
        return found

    def load(
        self,
        yaml_path: Path,
        image_path: Path,
        *,
        max_pixels: int,
        confine_to: Path | None = None,
        image_sha256: str | None = None,
        resolution_range_m: tuple[float, float] | None = None,
        max_extent_m: float | None = None,
    ) -> OccupancyMap:
        """The map of ``yaml_path``, decoded now or taken from the cache.

        ``image_path`` is the image the YAML names (already resolved by the caller), used only
        for the key; ``image_sha256`` saves hashing it when it is already known to be right.
        The limits are :func:`~mapserver.maps.load_map`'s, checked on a cached map too.
        """

        def load() -> OccupancyMap:
            return load_map(
                yaml_path,
                max_pixels=max_pixels,
                confine_to=confine_to,
                resolution_range_m=resolution_range_m,
                max_extent_m=max_extent_m,
            )

        if self.capacity == 0:
            return load()
        try:
            yaml_digest = hashlib.sha256(Path(yaml_path).read_bytes()).hexdigest()
            image_digest = self.digest(image_path, image_sha256)
        except OSError:
            # Let the loader report the problem with its own, precise message.
            return load()
        key = (yaml_digest, image_digest.lower())
        with self._lock:
            cached = self._maps.get(key)
            if cached is not None:
                self._maps.move_to_end(key)
                self.hits += 1
        if cached is not None:
            # Same content, another bundle: check the size limit and the paths as for a fresh load.
            # Anything wrong: the loader reports it with its own, precise message.
            too_big = cached.width * cached.height > max_pixels
            if max_extent_m is not None:
                too_big |= max(cached.width, cached.height) * cached.resolution > max_extent_m
            if resolution_range_m is not None:
                low, high = resolution_range_m
                too_big |= not low <= cached.resolution <= high
            if too_big or not _inside(confine_to, yaml_path, image_path):
                return load()
            return _renamed(cached, Path(yaml_path), Path(image_path))
        loaded = load()
        loaded.state.flags.writeable = False
        loaded.occupancy.flags.writeable = False
        with self._lock:
            self.misses += 1
            self._maps[key] = loaded
            self._maps.move_to_end(key)
            while len(self._maps) > self.capacity:
                self._maps.popitem(last=False)
        return loaded

    def clear(self) -> None:
        with self._lock:
            self._maps.clear()


def _inside(root: Path | None, *paths: Path) -> bool:
    """Whether every path resolves inside ``root`` (no root: yes; unresolvable: no)."""
    if root is None:
        return True
    try:
        top = Path(root).resolve()
        return all(Path(p).resolve().is_relative_to(top) for p in paths)
    except (OSError, RuntimeError):  # RuntimeError: a symlink loop before Python 3.13
        return False


def _renamed(m: OccupancyMap, yaml_path: Path, image_path: Path) -> OccupancyMap:
    """The cached map, with this bundle's paths in its source fields and warnings."""
    warnings = m.warnings
    if m.source is not None:
        warnings = tuple(w.replace(str(m.source), str(yaml_path)) for w in warnings)
    if m.image is not None:
        warnings = tuple(w.replace(str(m.image), str(image_path)) for w in warnings)
    return replace(m, source=yaml_path, image=image_path, warnings=warnings)
