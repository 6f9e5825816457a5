"""The operator's window: server-rendered pages, a JSON API (its OpenAPI schema at
``/openapi.json``, browsable at ``/docs``), the store's map files for robots, ``/healthz`` and
``/metrics``.

Read-mostly: the pages read the folders (through :class:`~mapserver.web.index.BundleIndex`),
the daemon's status file and the map store; the only writes are the review actions (approve,
reject, rollback), made through the same :class:`~mapserver.fleet.store.FleetStore` methods as
the command line.
"""

# No "from __future__ import annotations": FastAPI reads the endpoints' annotations at run time,
# and some name dependencies defined inside create_app.
import dataclasses
import hashlib
import logging
import re
import threading
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import datetime, timedelta, timezone
from http import HTTPStatus
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, FastAPI, Form, Header, HTTPException, Query, Request
from fastapi import Path as PathParam
from fastapi.exception_handlers import (
    http_exception_handler,
    request_validation_exception_handler,
)
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, PlainTextResponse, RedirectResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi.templating import Jinja2Templates
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from mapserver import __version__
from mapserver.bundle import BUNDLE_ID_RE
from mapserver.config import DEMO_MARKER, Config
from mapserver.errors import MapserverError, StoreError
from mapserver.fleet.db import MAX_ROW_ID
from mapserver.fleet.model import STATES, ChangeInfo, VersionInfo
from mapserver.maps import load_map
from mapserver.status import Report, report
from mapserver.web import pictures, security
from mapserver.web.index import BundleIndex, ResultRow, cursor, parse_cursor, read_yaml
from mapserver.web.metrics import MapserverCollector

log = logging.getLogger(__name__)
HERE = Path(__file__).parent

# A larger id or version from a request names no row, and would reach the store as an
# OverflowError (a 500): refused where it comes in (422).
RowId = Annotated[int, PathParam(ge=0, le=MAX_ROW_ID)]


# -- API schemas ---------------------------------------------------------------------------------


class BundleOut(BaseModel):
    bundle: str
    robot: str
    stamp: str
    processed_at: str
    status: str
    added: int
    removed: int
    score: float | None
    trusted: bool | None
    map: str | None
    map_version: int | None
    warnings: int

    @staticmethod
    def of(row: ResultRow) -> "BundleOut":
        return BundleOut(
            bundle=row.bundle_id,
            robot=row.robot,
            stamp=row.stamp,
            processed_at=row.processed_at,
            status=row.status,
            added=row.added,
            removed=row.removed,
            score=row.score,
            trusted=row.trusted,
            map=row.map_name,
            map_version=row.map_version,
            warnings=row.warnings,
        )


class BundlePage(BaseModel):
    items: list[BundleOut]
    next: str | None
    """Pass as ``before`` for the next (older) page; null on the last page."""


class FailureOut(BaseModel):
    bundle: str
    failed_at: str
    stage: str
    reason: str


class FailurePage(BaseModel):
    items: list[FailureOut]
    next: str | None


class VersionOut(BaseModel):
    version: int
    created_at: str
    sha256: str
    note: str
    changes: list[int]

    @staticmethod
    def of(v: VersionInfo) -> "VersionOut":
        return VersionOut(
            version=v.version,
            created_at=v.created_at,
            sha256=v.sha256,
            note=v.note,
            changes=list(v.changes),
        )


class MapOut(BaseModel):
    name: str
    current_version: int
    width: int
    height: int
    resolution: float
    origin: list[float]
    bundles: int
    changes: dict[str, int]
    versions: list[VersionOut] | None = None


class ChangeOut(BaseModel):
    id: int
    map: str
    kind: str
    state: str
    polygon: list[list[float]]
    first_seen: str
    last_seen: str
    sessions: int
    contradicted: int
    robots: list[str]
    bundles: list[str]
    version: int | None
    note: str
    history: list[dict[str, str]] | None = None

    @staticmethod
    def of(c: ChangeInfo, history: list[dict[str, str]] | None = None) -> "ChangeOut":
        return ChangeOut.model_validate({**dataclasses.asdict(c), "history": history})


class ChangePage(BaseModel):
    items: list[ChangeOut]
    next: int | None


class Rollback(BaseModel):
    version: Annotated[int, Field(ge=0, le=MAX_ROW_ID)]


class Health(BaseModel):
    status: str
    version: str
    daemon_running: bool
    degraded: bool
    results_indexed: int


# -- the application ----------------------------------------------------------------------------


class _Stores:
    """One FleetStore per worker thread (SQLite connections stay in their thread), opened on
    first use; none when the fleet map is off or no store exists yet."""

    def __init__(self, config: Config) -> None:
        self.config = config
        self._local = threading.local()

    @contextmanager
    def get(self) -> Iterator[Any]:
        from mapserver.fleet.store import FleetStore

        if self.config.maps is None or not (self.config.maps / "store.db").exists():
            yield None
            return
        store = getattr(self._local, "store", None)
        if store is None:
            store = FleetStore(self.config.maps, self.config.update, create=False, check=False)
            self._local.store = store
        yield store


class _Pictures:
    """Rendered map pictures, keyed by what they show (small LRU)."""

    def __init__(self, capacity: int = 16) -> None:
        self.capacity = capacity
        self._items: OrderedDict[tuple[Any, ...], bytes | None] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: tuple[Any, ...], make: Any) -> bytes | None:
        with self._lock:
            if key in self._items:
                self._items.move_to_end(key)
                return self._items[key]
        value: bytes | None = make()
        with self._lock:
            self._items[key] = value
            while len(self._items) > self.capacity:
                self._items.popitem(last=False)
        return value


def _page(rows: list[Any], limit: int) -> tuple[list[Any], str | None]:
    """The first ``limit`` of ``limit + 1`` rows fetched, and the cursor of the next page (None
    when there is none)."""
    return rows[:limit], (cursor(rows[limit - 1].key) if len(rows) > limit else None)


def _when(stamp: str) -> str:
    """``2026-11-21T10:15:00Z`` as ``11-21 10:15``: short enough for a table cell."""
    return stamp[5:16].replace("T", " ") if len(stamp) >= 16 else stamp


# An entity-tag of an If-None-Match list, weak or strong (RFC 9110 8.8.3).
_ENTITY_TAG = re.compile(r'(?:W/)?("[\x21\x23-\x7e\x80-\xff]*")')


def _none_match(if_none_match: str, tag: str) -> bool:
    """Whether ``If-None-Match`` matches our ``tag``: ``*``, or one of its tags by the weak
    comparison (RFC 9110 13.1.2), which ignores ``W/``: a cache or proxy may weaken a tag."""
    if if_none_match.strip() == "*":
        return True
    return tag.removeprefix("W/") in _ENTITY_TAG.findall(if_none_match)


def _day_ago() -> str:
    return (datetime.now(timezone.utc) - timedelta(days=1)).isoformat().replace("+00:00", "Z")


def create_app(config: Config, *, index: BundleIndex | None = None) -> FastAPI:
    """The web application for ``config``'s folders and map store."""
    web = config.web
    page_size = web.page_size if web is not None else 50
    token = security.read_token(web.token_file if web is not None else None)
    if index is None:  # not "or": an index is falsy while it is empty (__len__)
        index = BundleIndex(config.outbox, config.failed)
    stores = _Stores(config)
    pics = _Pictures()
    etags: dict[tuple[str, int, int], str] = {}
    templates = Jinja2Templates(directory=str(HERE / "templates"))
    templates.env.globals.update(version=__version__, state_colours=pictures.STATE_COLOURS)
    templates.env.filters["when"] = _when
    app = FastAPI(
        title="mapserver",
        version=__version__,
        description="Results of robot map bundles, the fleet map's tracked changes and versions.",
    )
    app.state.index = index
    app.mount("/static", StaticFiles(directory=str(HERE / "static")), name="static")
    registry = CollectorRegistry(auto_describe=True)

    def fleet_figures() -> list[dict[str, Any]] | None:
        with stores.get() as store:
            if store is None:
                return None
            return [
                {"name": m.name, "current_version": m.current_version, "counts": m.counts}
                for m in store.maps()
            ]

    registry.register(
        MapserverCollector(config, index, lambda: report(config, recent=False), fleet_figures)
    )

    # -- helpers ---------------------------------------------------------------------------

    def session_of(request: Request) -> security.Session | None:
        return security.read_session(token, request.cookies.get(security.COOKIE))

    def render(
        request: Request, template: str, status_code: int = 200, **context: Any
    ) -> HTMLResponse:
        session = session_of(request)
        context.update(
            request=request,
            session=session,
            csrf=security.csrf_token(token, session) if token and session else "",
            review_enabled=token is not None,
            mode=config.update.mode,
            fleet_on=config.maps is not None,
        )
        return templates.TemplateResponse(request, template, context, status_code=status_code)

    def bundle_dir(folder: Path, bundle_id: str) -> Path:
        if not BUNDLE_ID_RE.fullmatch(bundle_id):
            raise HTTPException(404, "no such bundle")
        path = folder / bundle_id
        if path.is_symlink() or not path.is_dir():
            raise HTTPException(404, "no such bundle")
        return path

    def safe_file(folder: Path, name: str) -> Path:
        path = folder / name
        try:
            real = path.resolve(strict=True)
        except (OSError, RuntimeError):
            raise HTTPException(404, "no such file") from None
        if path.is_symlink() or not real.is_relative_to(folder.resolve()) or not real.is_file():
            raise HTTPException(404, "no such file")
        return real

    def etag_of(path: Path) -> str:
        st = path.stat()
        key = (str(path), st.st_mtime_ns, st.st_size)
        tag = etags.get(key)
        if tag is None:
            tag = etags[key] = '"' + hashlib.sha256(path.read_bytes()).hexdigest()[:32] + '"'
        return tag

    def send(request: Request, path: Path, media_type: str, if_none_match: str | None) -> Response:
        tag = etag_of(path)
        headers = {"ETag": tag, "Cache-Control": "no-cache"}
        if if_none_match is not None and _none_match(if_none_match, tag):
            return Response(status_code=304, headers=headers)
        if request.method == "HEAD":  # what a GET would send, without the body
            headers["Content-Length"] = str(path.stat().st_size)
            return Response(media_type=media_type, headers=headers)
        return Response(path.read_bytes(), media_type=media_type, headers=headers)

    def require_token(authorization: Annotated[str | None, Header()] = None) -> str:
        """API review actions: ``Authorization: Bearer <token>``."""
        if token is None:
            raise HTTPException(403, "review actions are off: no web.token_file is configured")
        given = (authorization or "").removeprefix("Bearer ").strip()
        if not given or not security.same(given, token):
            raise HTTPException(401, "a valid token is needed (Authorization: Bearer <token>)")
        return "api (token)"

    def form_actor(request: Request, csrf: str) -> str:
        session = session_of(request)
        if token is None:
            raise HTTPException(403, "review actions are off: no web.token_file is configured")
        if session is None:
            raise HTTPException(401, "sign in with the review token first")
        if not security.same(csrf, security.csrf_token(token, session)):
            raise HTTPException(403, "the form is stale or forged: reload the page")
        return f"{session.name} (web)"

    def store_call(fn: Any) -> Any:
        with stores.get() as store:
            if store is None:
                raise HTTPException(404, "the fleet map is off or has no maps yet")
            try:
                return fn(store)
            except StoreError as error:
                code = (
                    404
                    if (
                        "no map named" in error.problem
                        or "no change" in error.problem
                        or "has no version" in error.problem
                    )
                    else 409
                )
                raise HTTPException(code, error.reason) from None

    def daemon_report() -> Report:
        return report(config, recent=False)  # the index counts the last 24 h

    # -- health, metrics, files for robots ---------------------------------------------------

    @app.get("/healthz", response_model=Health, tags=["health"])
    def healthz() -> Health:
        r = daemon_report()
        # What a monitor reads first (session 58's review: "ok" with the daemon down).
        status = "daemon not running" if not r.running else "degraded" if r.degraded else "ok"
        return Health(
            status=status,
            version=__version__,
            daemon_running=r.running,
            degraded=r.degraded is not None,
            results_indexed=len(index),
        )

    @app.get("/metrics", response_class=PlainTextResponse, tags=["health"])
    def metrics() -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

    # HEAD beside GET on the files: FastAPI, unlike Starlette, does not answer HEAD on a GET
    # route, and robots and caches may ask for the headers alone. Out of the schema: FastAPI
    # would give both methods one operation id.
    @app.get("/maps/{name}/current.yaml", tags=["maps"])
    @app.head("/maps/{name}/current.yaml", include_in_schema=False)
    def current_yaml(
        request: Request, name: str, if_none_match: Annotated[str | None, Header()] = None
    ) -> Response:
        """The map's current version, byte for byte the store's file (ETag, If-None-Match)."""
        if config.maps is None or not BUNDLE_ID_RE.fullmatch(name):
            raise HTTPException(404, "no such map")
        return send(
            request,
            safe_file(config.maps / name, "current.yaml"),
            "application/yaml",
            if_none_match,
        )

    @app.get("/maps/{name}/files/{file}", tags=["maps"])
    @app.head("/maps/{name}/files/{file}", include_in_schema=False)
    def map_file(
        request: Request,
        name: str,
        file: str,
        if_none_match: Annotated[str | None, Header()] = None,
    ) -> Response:
        """A file of the map store: a version's image or YAML, keepout.*, changes.yaml."""
        if (
            config.maps is None
            or not BUNDLE_ID_RE.fullmatch(name)
            or not BUNDLE_ID_RE.fullmatch(file)
        ):
            raise HTTPException(404, "no such file")
        path = safe_file(config.maps / name, file)
        media = {".yaml": "application/yaml", ".png": "image/png"}.get(
            path.suffix, "image/x-portable-graymap"
        )
        return send(request, path, media, if_none_match)

    # -- API: bundles and failures -------------------------------------------------------------

    def api_cursor(before: str | None) -> tuple[str, str] | None:
        """The API's ``before``: a page's ``next``, or nothing (a mistyped cursor is refused,
        not read as the first page; the HTML pages, typed by people, are lenient)."""
        key = parse_cursor(before)
        if before and key is None:
            raise HTTPException(422, "before: not a page cursor (give the previous page's next)")
        return key

    @app.get("/api/bundles", response_model=BundlePage, tags=["bundles"])
    def api_bundles(
        before: str | None = None, limit: Annotated[int, Query(ge=1, le=1000)] = page_size
    ) -> BundlePage:
        rows, nxt = _page(index.results(limit + 1, api_cursor(before)), limit)
        return BundlePage(items=[BundleOut.of(r) for r in rows], next=nxt)

    @app.get("/api/bundles/{bundle_id}", tags=["bundles"])
    def api_bundle(bundle_id: str) -> dict[str, Any]:
        """The bundle's result.yaml, as JSON."""
        doc = read_yaml(bundle_dir(config.outbox, bundle_id) / "result.yaml")
        if doc is None:
            raise HTTPException(404, "no result for this bundle")
        return doc

    @app.get("/api/failures", response_model=FailurePage, tags=["bundles"])
    def api_failures(
        before: str | None = None, limit: Annotated[int, Query(ge=1, le=1000)] = page_size
    ) -> FailurePage:
        rows, nxt = _page(index.failures(limit + 1, api_cursor(before)), limit)
        return FailurePage(
            items=[
                FailureOut(
                    bundle=r.bundle_id, failed_at=r.failed_at, stage=r.stage, reason=r.reason
                )
                for r in rows
            ],
            next=nxt,
        )

    # -- API: maps, versions, changes ----------------------------------------------------------

    def map_out(store: Any, name: str, *, with_versions: bool) -> MapOut:
        m = store.map_info(name)
        lat = m.lattice
        versions = None
        if with_versions:
            versions = [VersionOut.of(v) for v in store.versions(name)]
        return MapOut(
            name=m.name,
            current_version=m.current_version,
            width=lat.width,
            height=lat.height,
            resolution=lat.resolution,
            origin=[lat.x0, lat.y0, m.origin_yaw],
            bundles=m.bundles,
            changes=m.counts,
            versions=versions,
        )

    @app.get("/api/maps", response_model=list[MapOut], tags=["maps"])
    def api_maps() -> list[MapOut]:
        with stores.get() as store:
            if store is None:
                return []
            return [map_out(store, m.name, with_versions=False) for m in store.maps()]

    @app.get("/api/maps/{name}", response_model=MapOut, tags=["maps"])
    def api_map(name: str) -> MapOut:
        return store_call(lambda s: map_out(s, name, with_versions=True))  # type: ignore[no-any-return]

    def change_page(
        store: Any, name: str, state: str | None, before: int | None, limit: int
    ) -> tuple[list[ChangeInfo], int | None]:
        rows = store.changes(
            name, state=state, before_id=before, limit=limit + 1, newest_first=True
        )
        page = rows[:limit]
        return page, (page[-1].id if len(rows) > limit else None)

    @app.get("/api/maps/{name}/changes", response_model=ChangePage, tags=["changes"])
    def api_changes(
        name: str,
        state: Annotated[str | None, Query(pattern="^(" + "|".join(STATES) + ")$")] = None,
        before: Annotated[int | None, Query(ge=0, le=MAX_ROW_ID)] = None,
        limit: Annotated[int, Query(ge=1, le=1000)] = page_size,
    ) -> ChangePage:
        page, nxt = store_call(lambda s: change_page(s, name, state, before, limit))
        return ChangePage(items=[ChangeOut.of(c) for c in page], next=nxt)

    @app.get("/api/changes/{change_id}", response_model=ChangeOut, tags=["changes"])
    def api_change(change_id: RowId) -> ChangeOut:
        return store_call(lambda s: ChangeOut.of(s.change(change_id), s.history(change_id)))  # type: ignore[no-any-return]

    @app.post("/api/changes/{change_id}/approve", response_model=VersionOut, tags=["changes"])
    def api_approve(change_id: RowId, actor: Annotated[str, Depends(require_token)]) -> VersionOut:
        v = store_call(lambda s: s.approve(change_id, actor=actor))
        return VersionOut.of(v)

    @app.post("/api/changes/{change_id}/reject", response_model=ChangeOut, tags=["changes"])
    def api_reject(change_id: RowId, actor: Annotated[str, Depends(require_token)]) -> ChangeOut:
        return store_call(lambda s: ChangeOut.of(s.reject(change_id, actor=actor)))  # type: ignore[no-any-return]

    @app.post("/api/maps/{name}/rollback", response_model=VersionOut, tags=["maps"])
    def api_rollback(
        name: str, body: Rollback, actor: Annotated[str, Depends(require_token)]
    ) -> VersionOut:
        v = store_call(lambda s: s.rollback(name, body.version, actor=actor))
        return VersionOut.of(v)

    # -- pages --------------------------------------------------------------------------------

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def dashboard(request: Request) -> HTMLResponse:
        r = daemon_report()
        results_24h, failed_24h = index.counts_since(_day_ago())
        maps: list[Any] = []
        with stores.get() as store:
            if store is not None:
                maps = store.maps()
        return render(
            request,
            "dashboard.html",
            report=r,
            results_24h=results_24h,
            failed_24h=failed_24h,
            robots=index.robots(),
            maps=maps,
            recent=index.results(10),
            failures=index.failures(5),
            degraded=r.degraded,
            # A demo's folder: its daemon stopped once the samples were processed.
            demo=config.inbox.parent if (config.inbox.parent / DEMO_MARKER).is_file() else None,
        )

    @app.get("/bundles", response_class=HTMLResponse, include_in_schema=False)
    def bundles(request: Request, before: str | None = None) -> HTMLResponse:
        rows, nxt = _page(index.results(page_size + 1, parse_cursor(before)), page_size)
        return render(request, "bundles.html", rows=rows, next=nxt)

    @app.get("/bundles/{bundle_id}", response_class=HTMLResponse, include_in_schema=False)
    def bundle(request: Request, bundle_id: str) -> HTMLResponse:
        if not BUNDLE_ID_RE.fullmatch(bundle_id):
            raise HTTPException(404, "no such bundle")
        result_dir = config.outbox / bundle_id
        doc = (
            read_yaml(result_dir / "result.yaml")
            if result_dir.is_dir() and not result_dir.is_symlink()
            else None
        )
        if doc is None:
            failure = index.failure(bundle_id)
            if failure is None:
                raise HTTPException(404, "no such bundle")
            return render(request, "failure.html", failure=failure)
        return render(request, "bundle.html", bundle_id=bundle_id, doc=doc)

    @app.get("/bundles/{bundle_id}/{image}", include_in_schema=False)
    @app.head("/bundles/{bundle_id}/{image}", include_in_schema=False)
    def bundle_image(
        request: Request,
        bundle_id: str,
        image: str,
        if_none_match: Annotated[str | None, Header()] = None,
    ) -> Response:
        if image not in ("overlay.png", "diff.png"):
            raise HTTPException(404, "no such image")
        return send(
            request,
            safe_file(bundle_dir(config.outbox, bundle_id), image),
            "image/png",
            if_none_match,
        )

    @app.get("/failed", response_class=HTMLResponse, include_in_schema=False)
    def failed_page(request: Request, before: str | None = None) -> HTMLResponse:
        rows, nxt = _page(index.failures(page_size + 1, parse_cursor(before)), page_size)
        return render(request, "failed.html", rows=rows, next=nxt)

    @app.get("/maps", response_class=HTMLResponse, include_in_schema=False)
    def maps_page(request: Request) -> HTMLResponse:
        with stores.get() as store:
            maps = store.maps() if store is not None else []
        return render(request, "maps.html", maps=maps)

    @app.get("/maps/{name}", response_class=HTMLResponse, include_in_schema=False)
    def map_page(
        request: Request,
        name: str,
        state: str | None = None,
        before: Annotated[int | None, Query(ge=0, le=MAX_ROW_ID)] = None,
        versions: str | None = None,
    ) -> HTMLResponse:
        if state is not None and state not in STATES:
            state = None

        def gather(store: Any) -> dict[str, Any]:
            info = store.map_info(name)
            page, nxt = change_page(store, name, state, before, page_size)
            newest_first = list(reversed(store.versions(name)))
            # The newest page of versions unless all are asked for (a map publishing every
            # day has hundreds after a year).
            shown = newest_first if versions == "all" else newest_first[:page_size]
            return {
                "info": info,
                "changes": page,
                "next": nxt,
                "versions": shown,
                "versions_total": len(newest_first),
            }

        data = store_call(gather)
        return render(request, "map.html", name=name, state=state, **data)

    @app.get("/maps/{name}/picture.png", include_in_schema=False)
    def map_picture(name: str) -> Response:
        def make(store: Any) -> bytes | None:
            info = store.map_info(name)
            # What the picture shows changes only with the version and the changes' rows: one
            # aggregate says whether the cached picture is still right.
            key = (name, info.current_version, store.changes_digest(name))
            current = config.maps / name / "current.yaml"  # type: ignore[operator]

            def draw() -> bytes:
                return pictures.map_with_changes(
                    load_map(current).state, info.lattice, store.outlines(name)
                )

            return pics.get(key, draw)

        data = store_call(make)
        return Response(data, media_type="image/png", headers={"Cache-Control": "no-cache"})

    @app.get(
        "/maps/{name}/versions/{version}", response_class=HTMLResponse, include_in_schema=False
    )
    def version_page(request: Request, name: str, version: int) -> HTMLResponse:
        versions = {v.version: v for v in store_call(lambda s: s.versions(name))}
        if version not in versions:
            raise HTTPException(404, "no such version")
        v = versions[version]
        # The first version (the map as it was added) has nothing before it to show beside it.
        first = version - 1 not in versions
        return render(request, "version.html", name=name, v=v, changes=v.changes, first=first)

    @app.get("/maps/{name}/versions/{version}/change.png", include_in_schema=False)
    def version_picture(name: str, version: int) -> Response:
        versions = {v.version: v for v in store_call(lambda s: s.versions(name))}
        if version not in versions or version - 1 not in versions:
            raise HTTPException(404, "no earlier version to compare with")

        def draw() -> bytes | None:
            return pictures.version_change(
                load_map(versions[version - 1].yaml).state,
                load_map(versions[version].yaml).state,
                labels=(f"version {version - 1}", f"version {version}"),
            )

        data = pics.get(("version", name, version), draw)  # versions never change
        if data is None:
            raise HTTPException(404, "this version changed no cell")
        return Response(data, media_type="image/png", headers={"Cache-Control": "max-age=86400"})

    @app.get("/changes/{change_id}", response_class=HTMLResponse, include_in_schema=False)
    def change_page_html(request: Request, change_id: RowId) -> HTMLResponse:
        c, history = store_call(lambda s: (s.change(change_id), s.history(change_id)))
        return render(request, "change.html", c=c, history=history)

    @app.post("/changes/{change_id}/{action}", include_in_schema=False)
    def change_action(
        request: Request, change_id: RowId, action: str, csrf: Annotated[str, Form()] = ""
    ) -> Response:
        actor = form_actor(request, csrf)
        if action == "approve":
            store_call(lambda s: s.approve(change_id, actor=actor))
        elif action == "reject":
            store_call(lambda s: s.reject(change_id, actor=actor))
        else:
            raise HTTPException(404, "no such action")
        log.info("web: change %d %s by %s", change_id, action, actor)
        c = store_call(lambda s: s.change(change_id))
        return RedirectResponse(f"/maps/{c.map}", status_code=303)

    @app.post("/maps/{name}/rollback", include_in_schema=False)
    def rollback_form(
        request: Request,
        name: str,
        version: Annotated[int, Form(ge=0, le=MAX_ROW_ID)],
        csrf: Annotated[str, Form()] = "",
    ) -> Response:
        actor = form_actor(request, csrf)
        store_call(lambda s: s.rollback(name, version, actor=actor))
        log.info("web: map %s rolled back to version %d by %s", name, version, actor)
        return RedirectResponse(f"/maps/{name}", status_code=303)

    @app.get("/login", response_class=HTMLResponse, include_in_schema=False)
    def login_page(request: Request, error: str | None = None) -> HTMLResponse:
        return render(request, "login.html", error=error)

    @app.post("/login", include_in_schema=False)
    def login(
        request: Request,
        token_given: Annotated[str, Form(alias="token")],
        name: Annotated[str, Form()],
    ) -> Response:
        if token is None:
            raise HTTPException(403, "review actions are off: no web.token_file is configured")
        if not security.valid_name(name):
            return RedirectResponse("/login?error=name", status_code=303)
        if not security.same(token_given.strip(), token):
            log.warning("web: a sign-in with a wrong token (name %r)", name)
            return RedirectResponse("/login?error=token", status_code=303)
        response = RedirectResponse("/", status_code=303)
        response.set_cookie(
            security.COOKIE,
            security.new_session_cookie(token, name),
            max_age=security.SESSION_HOURS * 3600,
            httponly=True,
            samesite="strict",
            secure=request.url.scheme == "https",
        )
        return response

    @app.post("/logout", include_in_schema=False)
    def logout(request: Request, csrf: Annotated[str, Form()] = "") -> Response:
        # A forged form must not sign a reviewer out either. One from another site comes
        # without the session cookie (SameSite=Strict): nothing to sign out, and the cookie is
        # left alone, or the browser would drop it on that page's word.
        session = session_of(request)
        response = RedirectResponse("/", status_code=303)
        if token is None or session is None:
            return response
        if not security.same(csrf, security.csrf_token(token, session)):
            raise HTTPException(403, "the form is stale or forged: reload the page")
        response.delete_cookie(security.COOKIE)
        return response

    @app.exception_handler(MapserverError)
    def mapserver_error(request: Request, error: MapserverError) -> Response:
        return PlainTextResponse(error.reason, status_code=500)

    def for_a_person(request: Request) -> bool:
        """A page a browser asked for (not the API, the metrics, an image or a map file):
        its errors are pages too (session 58's review: /maps/nosuch answered JSON)."""
        path = request.url.path
        machine = path.startswith("/api/") or path in ("/metrics", "/healthz")
        files = path.endswith((".png", ".yaml", ".pgm"))
        return not machine and not files and "text/html" in request.headers.get("accept", "")

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, error: StarletteHTTPException) -> Response:
        if for_a_person(request) and error.status_code >= 400:
            title = HTTPStatus(error.status_code).phrase
            page = render(
                request,
                "error.html",
                status_code=error.status_code,
                code=error.status_code,
                title=title,
                detail=str(error.detail),
            )
            # What the error says in its headers (a 405's Allow, a 401's WWW-Authenticate).
            page.headers.update(error.headers or {})
            return page
        return await http_exception_handler(request, error)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, error: RequestValidationError) -> Response:
        if for_a_person(request):
            where = "; ".join(
                f"{'.'.join(str(x) for x in e.get('loc', ())[1:])}: {e.get('msg', '')}"
                for e in error.errors()
            )
            return render(
                request,
                "error.html",
                status_code=422,
                code=422,
                title="not a valid address",
                detail=where or "the address does not name anything here",
            )
        return await request_validation_exception_handler(request, error)

    return app
