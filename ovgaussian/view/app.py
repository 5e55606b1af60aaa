"""The browser viewer: a viser server showing the scene as Gaussian splats, with a GUI of mode, query, threshold,
legend and the inspect panel of a clicked Gaussian. All colours and answers come from ``ViewerState``.

viser (``pip install seggaussian[view]``) is imported here only, so the rest of the package never needs it.
"""

from __future__ import annotations

import contextlib
import html
import io
import threading
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from ovgaussian.view.cameras import (ViewerPose, camera_pose, centre_pose, frustum_wxyz, opening_camera,
                                     vertical_fov)
from ovgaussian.view.relevancy import DEFAULT_THRESHOLD, parse_queries
from ovgaussian.view.state import MODE_TITLES, Colouring, ViewerState
from seggaussian.util.atomic import atomic_path

#: Scene node name of the splats.
SPLATS_NODE = "/scene"
#: Scene node name of the marker on the clicked Gaussian.
PICK_NODE = "/picked"
#: Marker radius as a multiple of the clicked Gaussian's largest standard deviation.
PICK_MARKER_SIGMAS = 1.0
#: Marker colour (uint8 RGB): cyan, unlike every highlight colour.
PICK_MARKER_RGB = (0, 200, 255)
#: Step of the threshold slider.
THRESHOLD_STEP = 0.005
#: Legend rows shown (the most frequent labels).
LEGEND_ROWS = 24
#: Scene node of the camera frustums (one child per camera).
CAMERAS_NODE = "/cameras"
#: Frustum depth as a share of the scene's robust radius.
FRUSTUM_SCALE = 0.025
#: Frustum line thickness (screen pixels: thin whatever the distance, so the neighbours of the current camera do not
#: cover the view).
FRUSTUM_THICKNESS_PX = 2.0
#: Frustum colour (uint8 RGB): orange, unlike the pick marker and the highlight ramp's ends.
FRUSTUM_RGB = (255, 140, 0)
#: Frustums drawn at most (evenly spaced in the camera list beyond); every camera stays in the dropdown.
MAX_FRUSTUMS = 300
#: Percentile of the distances to the centre taken as the scene's robust radius (floaters ignored).
RADIUS_PERCENTILE = 90
#: The inspect panel before any click.
INSPECT_PROMPT = '<div style="font-size:0.85em">click a Gaussian</div>'
#: Export formats by file suffix.
EXPORT_SUFFIXES = (".html", ".viser")


def _swatch(rgb) -> str:
    r, g, b = (int(c) for c in rgb)
    return (f'<span style="display:inline-block;width:0.9em;height:0.9em;border-radius:2px;'
            f'background:rgb({r},{g},{b});margin-right:0.4em;vertical-align:-0.1em"></span>')


def legend_html(colouring: Colouring) -> str:
    """The legend of a colouring as HTML (swatch, name, count), most frequent first."""
    if not colouring.legend:
        return ""
    rows = [f"<div>{_swatch(row.rgb)}{html.escape(row.name)} <small>({row.count:,})</small></div>"
            for row in colouring.legend[:LEGEND_ROWS]]
    if len(colouring.legend) > LEGEND_ROWS:
        rows.append(f"<div><small>... {len(colouring.legend) - LEGEND_ROWS} more</small></div>")
    return f'<div style="font-size:0.85em;line-height:1.5">{"".join(rows)}</div>'


def inspect_html(info: dict | None) -> str:
    """The inspect panel of a clicked Gaussian (``ViewerState.inspect``)."""
    if info is None:
        return '<div style="font-size:0.85em" data-ov="inspect">no Gaussian under the click</div>'
    lines = [f'<b data-ov="index">Gaussian {info["index"]}</b>']
    if "predicted" in info:
        lines.append(f'predicted: <b data-ov="predicted">{html.escape(info["predicted"])}</b>')
        lines.append("top: " + ", ".join(f"{html.escape(t['name'])} {t['score']:.3f}" for t in info["top"]))
    if "relevancy" in info:
        lines.append("relevancy: " + ", ".join(f"{html.escape(q)} {r:.3f}" for q, r in info["relevancy"].items()))
    if "ground_truth" in info:
        lines.append(f'ground truth: <b data-ov="ground_truth">{html.escape(info["ground_truth"])}</b>')
    if "instance" in info:
        lines.append(f"instance: {info['instance']}")
    return f'<div style="font-size:0.85em;line-height:1.5" data-ov="inspect">{"<br>".join(lines)}</div>'


class QueryViewer:
    """A viser server showing ``state``'s scene; the GUI drives ``state`` and recolours the splats.

    Args:
        state: the scene and its answers.
        host, port: where to serve (viser takes the next free port when ``port`` is busy; 0: any free port).
        mode: the mode to start in (None: ``query`` when ``queries`` is given, else ``rgb``).
        queries: the query text to start with (comma-separated).
        threshold: the relevancy threshold to start with.
    """

    def __init__(self, state: ViewerState, host: str = "127.0.0.1", port: int = 8080, mode: str | None = None,
                 queries: str = "", threshold: float = DEFAULT_THRESHOLD, verbose: bool = False) -> None:
        import viser  # optional dependency (the "view" extra): imported by the viewer only

        self.state = state
        mode = mode or ("query" if parse_queries(queries) and "query" in state.modes else "rgb")
        if mode not in state.modes:
            raise ValueError(f"{state.scene.source}: mode {mode!r} is not available "
                             f"(available: {', '.join(state.modes)}; the query and predicted modes need --run, "
                             "the ground-truth modes --dataset/--scene)")
        if not 0.0 <= threshold <= 1.0:
            raise ValueError(f"{state.scene.source}: threshold {threshold} is outside [0, 1]")
        self.host = host
        self._verbose = verbose
        with self._viser_prints():
            self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
        self.port = self.server.get_port()
        self.last: Colouring | None = None
        self.last_seconds: dict = {}
        self.last_pick: dict | None = None
        self.last_camera: int | None = None  # the scene camera a client was last moved to
        self.start_camera: int | None = None  # the scene camera the viewer opens at
        self._at_camera: int | None = None  # the camera whose frustum is hidden
        self._marker = None  # the scene node marking the clicked Gaussian
        self._apply_lock = threading.Lock()
        self._request_lock = threading.Lock()
        self._requested = 0
        self._title_to_mode = {MODE_TITLES[m]: m for m in state.modes}
        self._quiet = False

        try:
            self._build(mode, queries, threshold)
        except BaseException:  # a scene that cannot be coloured: no server left running
            self.stop()
            raise

    def _build(self, mode: str, queries: str, threshold: float) -> None:
        state = self.state
        server = self.server
        server.gui.configure_theme(show_share_button=False, control_width="medium")
        self._set_initial_camera()
        arrays = state.arrays
        self.splats = server.scene.add_gaussian_splats(SPLATS_NODE, arrays.centers, arrays.covariances, arrays.rgb,
                                                       arrays.opacities)
        self._add_frustums()
        gui = server.gui
        cameras = state.scene.cameras
        names = tuple(f"{i}: {view.name}" for i, view in enumerate(cameras))
        self.camera_input = gui.add_dropdown("Camera", names or ("(none)",),
                                             initial_value=names[self.start_camera] if names else "(none)",
                                             visible=bool(names), hint="Go to one of the scene's cameras (or click "
                                                                       "its frustum)")
        self.camera_input.on_update(self._on_camera_choice)
        self.show_cameras = gui.add_checkbox("Show cameras", True, visible=bool(names),
                                             hint="Draw the scene's cameras as frustums")
        self.show_cameras.on_update(lambda _event: self._hide_frustum(self._at_camera))
        self.mode_input = gui.add_dropdown("Mode", tuple(MODE_TITLES[m] for m in state.modes),
                                           initial_value=MODE_TITLES[mode])
        has_field = "query" in state.modes
        self.query_input = gui.add_text("Query", queries, visible=has_field,
                                        hint="Comma-separated phrases; each Gaussian goes to the most relevant one")
        self.threshold_input = gui.add_slider(
            "Threshold", 0.0, 1.0, THRESHOLD_STEP, float(threshold), visible=has_field,
            hint=f"Calibrated relevancy (the query's probability against the vocabulary and the negatives) below which "
                 f"Gaussians are greyed; the default {DEFAULT_THRESHOLD:g} suits every phrase")
        self.status = gui.add_markdown("")
        with gui.add_folder("Legend"):
            self.legend = gui.add_html("")
        with gui.add_folder("Inspect"):
            self.inspect_panel = gui.add_html(INSPECT_PROMPT)

        self.mode_input.on_update(self._on_gui)
        self.query_input.on_update(self._on_query)
        self.threshold_input.on_update(self._on_gui)
        server.scene.on_click()(self._on_click)
        self.apply()

    # --- properties ------------------------------------------------------------------------------------
    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def mode(self) -> str:
        return self._title_to_mode[self.mode_input.value]

    @property
    def queries(self) -> tuple[str, ...]:
        return parse_queries(self.query_input.value)

    # --- updates -----------------------------------------------------------------------------------------
    def _set_initial_camera(self) -> None:
        """Open at the scene camera that sees the most Gaussians, or without cameras inside the splat at its centre
        (``cameras.centre_pose``)."""
        cameras = self.state.scene.cameras
        means = self.state.arrays.centers
        if cameras:
            self.start_camera = opening_camera(cameras, means)
            pose = camera_pose(cameras[self.start_camera].camera)
        else:
            self.start_camera = None
            pose = centre_pose(means)
        camera = self.server.initial_camera
        camera.fov = float(pose.fov)
        camera.up = tuple(float(v) for v in pose.up)
        camera.position = tuple(float(v) for v in pose.position)
        camera.look_at = tuple(float(v) for v in pose.look_at)

    def _add_frustums(self) -> None:
        """Draw the scene's cameras as filled frustums (at most ``MAX_FRUSTUMS``); a click on one moves that client
        there."""
        cameras = self.state.scene.cameras
        self.frustums = {}
        if not cameras:
            return
        means = self.state.arrays.centers
        radius = 1.0
        if len(means):
            centre = np.median(means, axis=0)
            radius = float(np.percentile(np.linalg.norm(means - centre, axis=1), RADIUS_PERCENTILE)) or 1.0
        shown = np.unique(np.linspace(0, len(cameras) - 1, min(len(cameras), MAX_FRUSTUMS)).round().astype(int))
        for i in shown:
            view = cameras[int(i)]
            handle = self.server.scene.add_camera_frustum(
                f"{CAMERAS_NODE}/{int(i):05d}", fov=vertical_fov(view.camera),
                aspect=view.camera.width / view.camera.height, scale=FRUSTUM_SCALE * radius, color=FRUSTUM_RGB,
                wxyz=tuple(float(v) for v in frustum_wxyz(view.camera)),
                position=tuple(float(v) for v in view.camera.center), thickness=FRUSTUM_THICKNESS_PX,
                thickness_units="screen", variant="filled")
            handle.on_click(lambda event, index=int(i): self.go_to_camera(index, event.client))
            self.frustums[int(i)] = handle
        self._hide_frustum(self.start_camera)

    def _hide_frustum(self, index: int | None) -> None:
        """Hide the frustum of the camera the view is at (seen from its apex it would cross the view), show the
        others (none when "Show cameras" is off)."""
        self._at_camera = index
        show = getattr(self, "show_cameras", None)
        shown = show is None or bool(show.value)
        for i, handle in self.frustums.items():
            handle.visible = shown and i != index

    def go_to_camera(self, index: int, client=None) -> ViewerPose:
        """Move ``client``'s view (every connected client when None) to scene camera ``index``; its pose."""
        cameras = self.state.scene.cameras
        if not 0 <= int(index) < len(cameras):
            raise IndexError(f"{self.state.scene.source}: no camera {index} (the scene has {len(cameras)})")
        pose = camera_pose(cameras[int(index)].camera)
        clients = [client] if client is not None else list(self.server.get_clients().values())
        for each in clients:
            with each.atomic():
                each.camera.fov = float(pose.fov)
                each.camera.up_direction = tuple(float(v) for v in pose.up)
                each.camera.position = tuple(float(v) for v in pose.position)
                each.camera.look_at = tuple(float(v) for v in pose.look_at)
        self.last_camera = int(index)
        self._hide_frustum(int(index))
        return pose

    def _on_camera_choice(self, event) -> None:
        if self._quiet or not self.state.scene.cameras:
            return
        index = int(str(self.camera_input.value).split(":", 1)[0])
        self.go_to_camera(index, getattr(event, "client", None))

    def _on_gui(self, _event) -> None:
        if not self._quiet:
            self.request_apply()

    def _on_query(self, _event) -> None:
        if self._quiet:
            return
        if self.queries and self.mode != "query" and "query" in self.state.modes:
            self.mode_input.value = MODE_TITLES["query"]  # runs request_apply through the dropdown's callback
            return
        self.request_apply()

    def request_apply(self) -> None:
        """Recolour for the GUI's current values; a request overtaken by a newer one while waiting is dropped
        (typing a query recolours for the latest text, not for every keystroke)."""
        with self._request_lock:
            self._requested += 1
            mine = self._requested
        with self._apply_lock:
            if mine != self._requested:
                return
            try:
                self.apply()
            except Exception:  # noqa: BLE001 -- apply() has put the error in the status line; keep serving
                pass

    def apply(self) -> Colouring:
        """Compute the colours of the GUI's current mode/query/threshold and send them to the clients."""
        start = time.perf_counter()
        try:
            colouring = self.state.colouring(self.mode, self.queries, float(self.threshold_input.value))
        except Exception as error:  # noqa: BLE001 -- shown in the GUI; the viewer keeps running
            self.status.content = f"**error:** {' '.join(str(error).split())}"
            raise
        scored = time.perf_counter()
        self.splats.rgbs = colouring.rgb
        sent = time.perf_counter()
        self.status.content = f"{colouring.status} ({sent - start:.2f} s)"
        self.legend.content = legend_html(colouring)
        self.last = colouring
        self.last_seconds = {"colouring": scored - start, "send": sent - scored, "total": sent - start}
        return colouring

    def set(self, mode: str | None = None, queries: str | None = None, threshold: float | None = None) -> Colouring:
        """Set GUI values from Python (as a user would) and recolour once."""
        if mode is not None and mode not in self.state.modes:
            raise ValueError(f"{self.state.scene.source}: mode {mode!r} is not available "
                             f"(available: {', '.join(self.state.modes)})")
        with self._apply_lock:
            self._quiet = True  # the GUI callbacks fired by these assignments do not recolour
            try:
                if threshold is not None:
                    self.threshold_input.value = float(threshold)
                if queries is not None:
                    self.query_input.value = queries
                if mode is not None:
                    self.mode_input.value = MODE_TITLES[mode]
            finally:
                self._quiet = False
            return self.apply()

    # --- clicks ------------------------------------------------------------------------------------------
    def _on_click(self, event) -> None:
        self.inspect_ray(event.ray_origin, event.ray_direction)

    def inspect_ray(self, origin, direction) -> dict | None:
        """Pick the Gaussian under a ray, show it in the inspect panel (and a marker on it); its facts."""
        index = self.state.pick(origin, direction)
        info = None if index is None else self.state.inspect(index, self.queries if self.mode == "query" else ())
        self.inspect_panel.content = inspect_html(info)
        if info is not None:
            radius = float(self.state.radii[index]) * PICK_MARKER_SIGMAS
            self._marker = self.server.scene.add_icosphere(PICK_NODE, radius=radius, color=PICK_MARKER_RGB,
                                                           position=tuple(info["position"]))
        self.last_pick = info
        return info

    def clear_pick(self) -> None:
        """Remove the marker of the clicked Gaussian and empty the inspect panel."""
        if self._marker is not None:
            self._marker.remove()
            self._marker = None
        self.inspect_panel.content = INSPECT_PROMPT
        self.last_pick = None

    # --- export / stop --------------------------------------------------------------------------------------
    def export(self, path: Path) -> int:
        """Write the scene as it is coloured now: ``.html`` (viser's client with the scene embedded: one
        self-contained file) or ``.viser`` (viser's scene recording). Returns the bytes written."""
        path = Path(path)
        suffix = path.suffix.lower()
        if suffix not in EXPORT_SUFFIXES:
            raise ValueError(f"{path}: export to .html (self-contained page) or .viser (viser recording), "
                             f"not {path.suffix or 'a file without suffix'}")
        serializer = self.server.get_scene_serializer()
        data = serializer.as_html().encode() if suffix == ".html" else serializer.serialize()
        with atomic_path(path, suffix=suffix) as tmp:
            tmp.write_bytes(data)
        return len(data)

    def _viser_prints(self):
        """viser prints its banner and "Server stopped" on stdout (rich) whatever ``verbose`` says; they would
        break ``--json`` output, so they are dropped unless ``verbose`` (the command prints its own URL line)."""
        return contextlib.nullcontext() if self._verbose else contextlib.redirect_stdout(io.StringIO())

    def stop(self) -> None:
        with self._viser_prints():
            self.server.stop()


def wait_for_clients(viewer: QueryViewer, count: int = 1, timeout: float = 30.0) -> Sequence:
    """The connected clients once ``count`` are there (each with a camera reported); TimeoutError otherwise."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        clients = list(viewer.server.get_clients().values())
        ready = []
        for client in clients:
            try:
                client.camera.update_timestamp
            except AssertionError:  # no camera message yet
                continue
            ready.append(client)
        if len(ready) >= count:
            return ready
        time.sleep(0.05)
    raise TimeoutError(f"{viewer.url}: {count} client(s) did not connect within {timeout:.0f} s")
