"""A Python client of the live node's HTTP API (:mod:`wm.serve`), for controllers and notebooks
in other processes. Its methods carry the names of :class:`~wm.whatis.WhatIs`'s and return
plain dictionaries (the JSON the API sends; positions as lists of metres), so code written
against What Is in-process reads the same against a server.

    from wm.client import Client
    c = Client("http://127.0.0.1:8765", token=None)
    c.self_state()["position"]; c.region(x=10, y=0, radius_m=20, classes=["person"])

Only the standard library is used (``urllib``). A 4xx or 5xx answer raises :class:`ClientError`
with the server's ``detail``, which names the offending value.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from typing import Any

from core.errors import EngineError

#: the media type of an Arrow IPC stream (what /v1/sql and map windows answer when asked)
ARROW_STREAM = "application/vnd.apache.arrow.stream"


class ClientError(EngineError, RuntimeError):
    """The server refused a request (``status`` is the HTTP code) or could not be reached."""

    def __init__(self, message: str, status: int | None = None) -> None:
        super().__init__(message)
        self.status = status


class Client:
    """Calls to one server at ``base_url`` (e.g. ``http://127.0.0.1:8765``), with the bearer
    ``token`` if the server wants one; ``timeout_s`` per request."""

    def __init__(self, base_url: str, token: str | None = None, timeout_s: float = 30.0) -> None:
        self.base_url = base_url.rstrip("/")
        self.token, self.timeout_s = token, timeout_s

    def _headers(self) -> dict[str, str]:
        headers = {"Content-Type": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        return headers

    def _call(
        self,
        path: str,
        params: dict | None = None,
        body: dict | None = None,
        accept: str | None = None,
    ) -> Any:
        """The JSON answer of ``path``; with ``accept`` (a media type), the answer's bytes."""
        query = urllib.parse.urlencode(
            {k: v for k, v in (params or {}).items() if v is not None}, doseq=True
        )
        url = f"{self.base_url}{path}" + (f"?{query}" if query else "")
        headers = self._headers() | ({"Accept": accept} if accept else {})
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(url, data=data, headers=headers)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout_s) as r:
                return r.read() if accept else json.loads(r.read())
        except urllib.error.HTTPError as e:
            try:
                detail = json.loads(e.read() or b"null")
                detail = detail.get("detail", detail) if isinstance(detail, dict) else detail
            except ValueError:
                detail = e.reason
            raise ClientError(f"{path}: HTTP {e.code}: {detail}", e.code) from None
        except urllib.error.URLError as e:
            raise ClientError(f"{url}: cannot reach the server ({e.reason})") from None

    def status(self) -> dict:
        """Cycles, the newest cycle's time, lag, cycle time, frames read and skipped."""
        return self._call("/v1/status")

    def self_state(self, t_ns: int | None = None, frame: str = "world") -> dict:
        return self._call("/v1/self", {"t_ns": t_ns, "frame": frame})

    def entity(self, entity_id: int, t_ns: int | None = None, frame: str = "world") -> dict:
        return self._call(f"/v1/entities/{int(entity_id)}", {"t_ns": t_ns, "frame": frame})

    def region(
        self,
        x: float | None = None,
        y: float | None = None,
        radius_m: float | None = None,
        box: tuple[float, float, float, float] | None = None,
        classes: list[str] | None = None,
        statuses: list[str] | None = None,
        min_confidence: float = 0.0,
        levels: list[int] | None = None,
    ) -> dict:
        """Entities in a circle (x, y, radius_m) or a ``box`` (x_min, y_min, x_max, y_max),
        world metres, passing the filters."""
        params: dict[str, Any] = {"x": x, "y": y, "radius_m": radius_m}
        if box is not None:
            params.update(zip(("x_min", "y_min", "x_max", "y_max"), box, strict=True))
        params.update(
            {"class": classes, "status": statuses, "min_confidence": min_confidence,
             "level": levels}
        )  # fmt: skip
        return self._call("/v1/entities", params)

    def events(self, t_from_ns: int, t_to_ns: int, class_name: str | None = None) -> dict:
        return self._call(
            "/v1/events", {"t_from_ns": t_from_ns, "t_to_ns": t_to_ns, "class_name": class_name}
        )

    def simulate(
        self,
        plans: list[dict],
        level: str = "subsystem",
        horizon_s: float | None = None,
        goal_xy: tuple[float, float] | None = None,
        start: dict | None = None,
        traces: bool = False,
    ) -> dict:
        """What If with value judgment (``POST /v1/whatif``): ``plans`` as dictionaries, each
        ``{"name", "t_s", "xy"}`` (waypoints, world m) or ``{"name", "t_s", "speed_mps",
        "curvature_1pm"}`` (controls); per plan cost, risk, benefit, score, first collision,
        why, and the rolled-out path; ``best`` the highest score's index. ``start``: the state
        to roll out from (``{"xy", "yaw_rad", "speed_mps", "t0_ns"}``, world frame, as
        :meth:`whatif_start` gives it; default the self state now); ``traces``: also the
        per-step arrays at full precision (:class:`wm.remote.RemoteWhatIf` reads them)."""
        body = {"plans": plans, "level": level, "horizon_s": horizon_s,
                "goal_xy": None if goal_xy is None else list(goal_xy)}  # fmt: skip
        if start is not None:  # left out otherwise, so older servers get the body they know
            body["start"] = start
        if traces:
            body["traces"] = True
        return self._call("/v1/whatif", body=body)

    def whatif_start(self) -> dict:
        """The state What If rolls out from now (``GET /v1/whatif/start``): ``xy`` world m,
        ``yaw_rad``, ``speed_mps``, ``t0_ns``, and the ``cycle_t_ns`` it comes from."""
        return self._call("/v1/whatif/start")

    def set_plan(self, xy: list[list[float]] | None) -> dict:
        """Tell the node the current plan (``POST /v1/plan``): its path ``[[x, y], ...]``
        (world m), or None for none; the node's attention weighs entities near it higher."""
        return self._call("/v1/plan", body={"xy": xy})

    def map_window(
        self, level: str | int, x: float, y: float, half_m: float = 10.0,
        layers: tuple[str, ...] = ("elevation",),
    ) -> dict:  # fmt: skip
        """Layers of map ``level`` (name or 2..5) around world (x, y) m as JSON: ``values``
        by layer, rows south to north (NaN as None), ``origin`` (world m of cell [0, 0]'s
        south-west corner), ``resolution_m``, ``shape``, ``cycle_t_ns``."""
        params = {"x": x, "y": y, "half_m": half_m, "layers": ",".join(layers)}
        return self._call(f"/v1/maps/{level}", params)

    def get_grid_map(
        self,
        position_x: float,
        position_y: float,
        length_x: float,
        length_y: float,
        layers: tuple[str, ...] = (),
        level: str = "subsystem",
        frame_id: str = "world",
    ) -> dict:
        """grid_map's GetGridMap (``POST /v1/grid_map/get_grid_map``): the submap of
        ``length_x`` x ``length_y`` m around world (``position_x``, ``position_y``) of map
        ``level``, the ``layers`` asked (all when empty); ``map`` is a grid_map_msgs/GridMap
        (column-major, index (0, 0) at the largest x and y; wm.serve_ros)."""
        body = {"frame_id": frame_id, "position_x": position_x, "position_y": position_y,
                "length_x": length_x, "length_y": length_y, "layers": list(layers),
                "level": level}  # fmt: skip
        return self._call("/v1/grid_map/get_grid_map", body=body)

    def check_safety(
        self,
        polygons: list[dict | list[tuple[float, ...]]],
        compute_untraversable_polygon: bool = False,
        level: str = "subsystem",
    ) -> dict:
        """elevation_mapping's CheckSafety (``POST /v1/elevation_mapping/check_safety``):
        ``polygons`` as geometry_msgs/PolygonStamped dictionaries or as lists of world (x, y)
        or (x, y, z) m points; per polygon ``is_safe``, ``traversability`` (0..1, None when no
        cell is known), ``untraversable_polygons`` and ``why``."""
        body = {
            "polygons": [p if isinstance(p, dict) else _polygon_stamped(p) for p in polygons],
            "compute_untraversable_polygon": compute_untraversable_polygon,
            "level": level,
        }
        return self._call("/v1/elevation_mapping/check_safety", body=body)

    def is_path_valid(
        self,
        path: dict | list[tuple[float, float]],
        max_cost: int = 254,
        consider_unknown_as_obstacle: bool = False,
        stop_at_first_collision: bool = True,
        max_lookahead_distance: float = -1.0,
        level: str = "subsystem",
    ) -> dict:
        """Nav2's IsPathValid (``POST /v1/nav2/is_path_valid``): ``path`` as a nav_msgs/Path
        dictionary or a list of world (x, y) m positions (unstamped: driven at the default
        speed); ``is_valid``, ``invalid_pose_indices``, ``why`` and the What If ``plan`` it
        was judged by (wm.serve_ros)."""
        if not isinstance(path, dict):
            path = {"header": {"frame_id": "world"}, "poses": [
                {"header": {"frame_id": "world"}, "pose": {"position": {"x": x, "y": y}}}
                for x, y in path
            ]}  # fmt: skip
        body = {"path": path, "max_cost": max_cost,
                "consider_unknown_as_obstacle": consider_unknown_as_obstacle,
                "stop_at_first_collision": stop_at_first_collision,
                "max_lookahead_distance": max_lookahead_distance, "level": level}  # fmt: skip
        return self._call("/v1/nav2/is_path_valid", body=body)

    def attention(self, level: str | int = 4) -> dict:
        """Entities of SP ``level`` the node attends to, each with ``why``."""
        return self._call("/v1/attention", {"level": level})

    def stream(self, timeout_s: float | None = None) -> Iterator[dict]:
        """The push stream (``GET /v1/stream``): one dictionary per server-sent event,
        ``{"event": "cycle" | "end", **data}``, until the server ends it (the end of the
        replay) or the caller stops iterating (which closes the connection). ``timeout_s``:
        the longest wait for a line (default the client's)."""
        req = urllib.request.Request(f"{self.base_url}/v1/stream", headers=self._headers())
        try:
            resp = urllib.request.urlopen(req, timeout=timeout_s or self.timeout_s)
        except urllib.error.HTTPError as e:
            raise ClientError(f"/v1/stream: HTTP {e.code}: {e.reason}", e.code) from None
        except urllib.error.URLError as e:
            raise ClientError(f"{self.base_url}: cannot reach the server ({e.reason})") from None
        with resp:
            yield from _sse_events(resp)

    def sql_table(self, query: str) -> Any:
        """:meth:`sql` as a ``pyarrow.Table`` (the server's Arrow IPC answer): its schema's
        metadata holds ``cycle_t_ns``, ``newest_cycle_t_ns`` and ``staleness_ns`` (JSON)."""
        import pyarrow as pa

        return pa.ipc.open_stream(self._call("/v1/sql", body={"query": query},
                                             accept=ARROW_STREAM)).read_all()  # fmt: skip

    def sql(self, query: str) -> dict:
        """One read-only SELECT: ``{"columns", "rows", "truncated", "cycle_t_ns",
        "newest_cycle_t_ns", "staleness_ns"}`` (``truncated`` always false: a result over the
        server's row or byte limit raises ClientError with status 413 and the limit in its
        words)."""
        return self._call("/v1/sql", body={"query": query})


def _polygon_stamped(points: list[tuple[float, ...]]) -> dict:
    """A geometry_msgs/PolygonStamped in the world frame of (x, y) or (x, y, z) m points."""
    pts = [dict(zip(("x", "y", "z"), (*p, 0.0)[:3], strict=True)) for p in points]
    return {"header": {"frame_id": "world"}, "polygon": {"points": pts}}


def _sse_events(lines: Any) -> Iterator[dict]:
    """Server-sent events from an iterable of byte lines: ``event:`` and ``data:`` fields up
    to a blank line make one event (comment lines, ``:``, are skipped); data is JSON."""
    event, data = "message", []
    for raw in lines:
        line = raw.decode("utf-8").rstrip("\r\n")
        if not line:
            if data:
                yield {"event": event, **json.loads("\n".join(data))}
            event, data = "message", []
        elif line.startswith(":"):
            continue
        elif line.startswith("event:"):
            event = line[6:].strip()
        elif line.startswith("data:"):
            data.append(line[5:].lstrip())
