"""A 3D recording of a run: a rerun ``.rrd`` file, frame by frame (``ssp run --record``).

:class:`Recorder` is fed the parser's input and answer for each frame
(:meth:`Recorder.log_frame`) and writes, on the timelines ``frame`` (the frame's position in
the run, 0-based) and ``time`` (its stamp, s):

* ``world``: the recording's classes (an ``AnnotationContext``, static: background, table and
  the five transition modes, :data:`ssp.viz.record_entities.CLASSES`), so the viewer's key
  has one entry per class, whatever the number of objects;
* ``world/cloud/objects``: the points of the object segments (labels >= 0; world frame, m),
  coloured by segment label (a fixed palette), at most ``max_points``;
  ``world/cloud/table`` and ``world/cloud/background``: the points of no segment on the
  table (within :data:`~ssp.viz.record_entities.TABLE_BAND` of z = 0) and elsewhere, by class
  (dim greys), smaller and each cut to a small evenly spaced subset
  (:func:`~ssp.viz.record_entities.split_cloud`), so they do not swamp the objects;
* ``world/objects/<id>``: each object's pose ``T_world_obj`` (a transform), its model mesh
  (``mesh``, object frame, logged once when the object appears) coloured by its transition
  mode (:data:`MODE_COLOURS`; slightly translucent, an ephemeral object, kept although
  unseen, more so: :data:`OBJECT_ALPHA`) and its one label, its id (``label``: a point of its
  mode's class above the top of the object, raised clear of its neighbours' labels, on a
  thin line down to the top, :func:`~ssp.viz.record_entities.place_labels`; ``mode`` and
  ``ephemeral`` shown when it is selected); an object that leaves the scene is cleared;
* ``world/hypotheses/<class>``: the frame's pose hypotheses, faint and without labels: one
  mesh per class instanced at every hypothesis pose (the mesh is logged once, the poses per
  frame);
* ``world/truth/<class>``: the ground truth, when given (simulated sequences), likewise;
* ``world/support``: arrows from each supporter's centre of mass (the table: the point on it
  below the object) to the centre of the object it carries, labelled with the fraction of the
  object's weight;
* ``world/camera``: the camera pose ``T_world_cam`` (OpenCV axes), when known, and with the
  intrinsics (when given) a ``Pinhole`` (the viewer draws its frustum); ``world/camera/depth``:
  the frame's depth image (``DepthImage``, uint16 mm, ``meter`` 1000) when given (an input
  that is a cloud has none, and none is made up), shown in a 2D view of its own;
* ``terms/scene/<term>``: the scene totals (sums over the objects) of the five log-probability
  terms (``stability``, ``collision``, ``support``, ``data``, ``transition``) and ``total``
  (``log Pr(s | C, D)``); ``terms/objects/<id>/<term>``: each object's terms, drawn in its
  term's colour and without a legend (the scene plot's six entries are the key);
* ``log``: one line per frame (objects, hypotheses, log-probability), the parser's warnings,
  rejected and removed objects, and failed frames (:meth:`Recorder.log_failure`).

rerun (``rerun-sdk``, the ``record`` extra) is imported only here, when a recording is made;
without it :func:`require_rerun` raises :class:`RecordingError` naming the install command.
Open a recording with :func:`view` (``ssp view RUN.rrd``) or the ``rerun`` viewer.
"""

from __future__ import annotations

import logging
import os
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ssp.errors import SSPError
from ssp.estimate import SceneEstimate
from ssp.scene import Frame
from ssp.viz.record_entities import (
    BACKGROUND_CLASS,
    CLASSES,
    MODE_COLOURS,
    TABLE_CLASS,
    depth_millimetres,
    mode_class,
    object_top,
    place_labels,
    split_cloud,
)

__all__ = [
    "DEFAULT_MAX_POINTS",
    "INSTALL_HINT",
    "MODE_COLOURS",
    "TERMS",
    "check_recording",
    "Recorder",
    "RecordingError",
    "RunRecording",
    "has_display",
    "label_colours",
    "prepare_view",
    "require_rerun",
    "view",
    "view_command",
]

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'sequential-scene-parsing[record]'"
#: Cloud points kept per frame (an evenly spaced subset of a larger cloud).
DEFAULT_MAX_POINTS = 50_000
#: The five log-probability terms, in :class:`ssp.probability.ObjectTerms` order.
TERMS = ("stability", "collision", "support", "data", "transition")
#: Series colour (RGB) per term.
TERM_COLOURS = {
    "stability": (230, 90, 60),
    "collision": (240, 200, 40),
    "support": (190, 90, 220),
    "data": (60, 180, 230),
    "transition": (90, 200, 110),
    "total": (235, 235, 235),
}
#: Segment colours (RGB, tab20 order); labels < 0 (table, background) are :data:`GREY`.
PALETTE = np.array(
    [
        (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
        (140, 86, 75), (227, 119, 194), (188, 189, 34), (23, 190, 207), (174, 199, 232),
        (255, 187, 120), (152, 223, 138), (255, 152, 150), (197, 176, 213), (196, 156, 148),
        (247, 182, 210), (219, 219, 141), (158, 218, 229), (57, 59, 121), (99, 121, 57),
    ],
    dtype=np.uint8,
)  # fmt: skip
GREY = np.array((110, 110, 110), dtype=np.uint8)
#: Object mesh opacity (0-255): seen, ephemeral (kept unseen). Slightly translucent, so the
#: support arrows between centres and the object's own points show through.
OBJECT_ALPHA = (200, 100)
#: Cloud point radius on screen (ui points) per part of the cloud.
POINT_RADIUS = {"background": 0.5, "table": 0.75, "objects": 2.0}
#: Distance (m) of the camera frustum's image plane from the camera centre.
FRUSTUM_DEPTH = 0.1
#: The viewer's eye is put at this fraction of the way from the objects to the camera.
EYE_DISTANCE = 0.6
HYPOTHESIS_RGBA = (210, 210, 210, 22)
TRUTH_RGBA = (255, 255, 255, 35)
SUPPORT_RGB = (250, 220, 60)
#: Meshes up to this many faces are sent with one vertex triple per face (flat shading: boxes
#: keep sharp edges); larger ones share vertices, with smooth normals.
FLAT_SHADING_MAX_FACES = 5000


class RecordingError(SSPError):
    """A recording cannot be made or shown: rerun is missing, the file cannot be written, no
    display to open the viewer on."""


def require_rerun() -> ModuleType:
    """The ``rerun`` module, or :class:`RecordingError` naming the install command."""
    try:
        import rerun
    except ImportError as exc:
        raise RecordingError(
            f"3D recordings need rerun (rerun-sdk), which is not installed: {INSTALL_HINT}"
        ) from exc
    return rerun


def check_recording(path: str | os.PathLike) -> None:
    """RecordingError unless a recording can be written to ``path``: rerun is installed,
    ``path`` is not a folder and its nearest existing parent is a writable folder (checked
    before a run writes anything; nothing is created here)."""
    require_rerun()
    p = Path(path)
    if p.is_dir():
        raise RecordingError(f"{p}: is a folder; give a file name such as run.rrd")
    base = next(a for a in (p.absolute().parent, *p.absolute().parents) if a.exists())
    if not base.is_dir() or not os.access(base, os.W_OK):
        raise RecordingError(f"{p}: cannot be written ({base} is not a writable folder)")


def label_colours(labels: np.ndarray | None, n: int) -> np.ndarray:
    """``(n, 3)`` uint8 RGB per point: :data:`PALETTE` by segment label (label modulo its
    length), :data:`GREY` for negative labels or when there are no labels."""
    if labels is None:
        return np.tile(GREY, (n, 1))
    labels = np.asarray(labels, dtype=np.int64)
    out = PALETTE[np.mod(labels, len(PALETTE))]
    out[labels < 0] = GREY
    return out


def _mesh_arrays(mesh) -> dict[str, np.ndarray]:
    """Mesh3D fields of a trimesh (object frame, m)."""
    faces = np.asarray(mesh.faces, dtype=np.uint32)
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    if len(faces) <= FLAT_SHADING_MAX_FACES:
        normals = np.repeat(np.asarray(mesh.face_normals, dtype=np.float32), 3, axis=0)
        return {
            "vertex_positions": vertices[faces].reshape(-1, 3),
            "vertex_normals": normals,
            "triangle_indices": np.arange(3 * len(faces), dtype=np.uint32).reshape(-1, 3),
        }
    return {
        "vertex_positions": vertices,
        "vertex_normals": np.asarray(mesh.vertex_normals, dtype=np.float32),
        "triangle_indices": faces,
    }


class Recorder:
    """Writes a rerun recording of a run to ``path`` (``.rrd``), one frame at a time.

    Args:
        path: the ``.rrd`` file to write (replaced; its folder is created).
        library: class name -> :class:`ssp.library.model.ObjectModel` (``mesh``, object frame,
            m; ``center_of_mass``).
        max_points: cloud points kept per frame.
        application_id, recording_id: rerun's names for the recording (default: ``ssp``, a
            new random id).

    Use as a context manager, or call :meth:`close` (the file is complete only then).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        library: Mapping[str, Any],
        *,
        max_points: int = DEFAULT_MAX_POINTS,
        application_id: str = "ssp",
        recording_id: str | None = None,
    ) -> None:
        check_recording(path)
        rr = require_rerun()
        self._rr = rr
        self.path = Path(path)
        self.library = library
        self.max_points = int(max_points)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot create its folder: {exc}") from exc
        self._rec = rr.RecordingStream(application_id, recording_id=recording_id)
        self._rec.set_log_time_enabled(False)  # wall clock: the same input, the same content
        try:
            self._rec.save(self.path)
        except Exception as exc:  # rerun raises its own errors for an unwritable file
            raise RecordingError(f"{self.path}: cannot write the recording: {exc}") from exc
        self._meshes: dict[str, dict[str, np.ndarray]] = {}
        self._objects: set[str] = set()  # ids whose mesh is logged and not cleared
        self._instanced: set[str] = set()  # instanced entities whose mesh is logged
        self._styled: set[str] = set()  # ids whose term series have their style
        self._depth_shown = False  # a depth image is logged and not cleared
        self._closed = False
        self._layout_sent = False
        self._log_static()

    # ------------------------------------------------------------------ setup
    def _log_static(self) -> None:
        rr, rec = self._rr, self._rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        rec.log(
            "world",
            rr.AnnotationContext(
                [rr.AnnotationInfo(id=i, label=name, color=rgb) for i, name, rgb in CLASSES]
            ),
            static=True,
        )
        for name in (*TERMS, "total"):
            rec.log(
                f"terms/scene/{name}",
                rr.SeriesLines(colors=[TERM_COLOURS[name]], names=[name]),
                static=True,
            )

    def _send_layout(
        self, frame: Frame | None, estimate: SceneEstimate | None, depth: bool = False
    ) -> None:
        """The viewer's layout (a blueprint): the 3D scene beside the term plots and the log,
        the eye at the first frame's camera (when known) looking at its objects; ``depth``:
        the first frame has a depth image, shown in a 2D view above the plots (the 3D view
        leaves it out: back-projected it would draw the cloud twice)."""
        self._layout_sent = True
        rr = self._rr
        bp = rr.blueprint
        eye = None
        if frame is not None and estimate is not None:
            if estimate.objects:
                target = np.mean([o.T_world_obj[:3, 3] for o in estimate.objects], axis=0)
            else:
                target = np.median(np.asarray(frame.points, dtype=float), axis=0)
            if frame.T_world_cam is not None:  # from the camera, a little closer
                cam = np.asarray(frame.T_world_cam, dtype=float)[:3, 3]
                position = target + EYE_DISTANCE * (cam - target)
            else:
                position = target + np.array([-0.3, -0.3, 0.3])
            eye = bp.EyeControls3D(
                position=position.tolist(), look_target=target.tolist(), eye_up=[0.0, 0.0, 1.0]
            )
        try:
            side = [
                bp.TimeSeriesView(origin="terms/scene", name="terms (scene)"),
                bp.TimeSeriesView(
                    origin="terms/objects",
                    name="terms (objects)",
                    plot_legend=bp.PlotLegend(visible=False),  # 5 per object: the scene's key
                ),
                bp.TextLogView(origin="log", name="log"),
            ]
            if depth:
                side.insert(0, bp.Spatial2DView(origin="world/camera", name="depth"))
            layout = bp.Blueprint(
                bp.Horizontal(
                    bp.Spatial3DView(
                        origin="world",
                        name="scene",
                        eye_controls=eye,
                        contents=["+ $origin/**", "- /world/camera/depth"],
                    ),
                    bp.Vertical(*side),
                    column_shares=[3, 2],
                ),
                bp.TimePanel(timeline="frame"),
                collapse_panels=False,
            )
            self._rec.send_blueprint(layout)
        except Exception as exc:  # a layout is a convenience: the viewer makes its own
            log.warning("rerun blueprint not sent (%s); the viewer picks a layout", exc)

    def _mesh(self, class_name: str) -> dict[str, np.ndarray]:
        if class_name not in self._meshes:
            self._meshes[class_name] = _mesh_arrays(self.library[class_name].mesh)
        return self._meshes[class_name]

    @staticmethod
    def _part(name: str) -> str:
        import rerun as rr

        return rr.escape_entity_path_part(str(name))

    def _set_time(self, index: int, stamp: float | None) -> None:
        self._rec.reset_time()
        self._rec.set_time("frame", sequence=int(index))
        if stamp is not None:
            self._rec.set_time("time", duration=float(stamp))

    def _text(self, text: str, level: str = "INFO") -> None:
        self._rec.log("log", self._rr.TextLog(text, level=level))

    # ------------------------------------------------------------------ frames
    def log_frame(
        self,
        index: int,
        frame: Frame,
        estimate: SceneEstimate,
        *,
        name: str | None = None,
        truth: Mapping[str, tuple[str, np.ndarray]] | None = None,
        camera: Any = None,
        depth: np.ndarray | None = None,
    ) -> None:
        """Log one parsed frame at ``frame`` = ``index`` and ``time`` = ``frame.stamp`` (s).

        Args:
            index: the frame's position in the run (0-based).
            frame: the parser's input (world-frame cloud, labels, hypotheses, camera pose).
            estimate: the parser's answer for ``frame``.
            name: the frame's name (file stem, BOP ``im_id``), for the log line.
            truth: ground truth ``{id: (class, T_world_obj (4, 4))}``, when known.
            camera: the intrinsics (:class:`ssp.camera.Camera`: ``width``, ``height``, ``fx``,
                ``fy``, ``cx``, ``cy``, pixels) of the frame's camera, when known: drawn as
                a frustum at ``frame.T_world_cam``.
            depth: the frame's depth image ``(H, W)`` (m; 0 or non-finite: no return) seen by
                ``camera``, when the input has one.

        Raises:
            RecordingError: ``depth`` without ``camera``, or not of ``camera``'s size.
        """
        if not self._layout_sent:
            self._send_layout(frame, estimate, depth is not None and camera is not None)
        self._set_time(index, frame.stamp)
        self._log_cloud(frame)
        self._log_camera(frame.T_world_cam, camera, depth)
        eye = None if frame.T_world_cam is None else np.asarray(frame.T_world_cam)[:3, 3]
        self._log_objects(estimate, eye)
        self._log_instanced(
            "world/hypotheses",
            [(h.class_name, h.T_world_obj) for h in frame.hypotheses],
            HYPOTHESIS_RGBA,
        )
        if truth is not None:
            self._log_instanced("world/truth", list(truth.values()), TRUTH_RGBA)
        self._log_support(estimate)
        self._log_terms(estimate)
        what = f"frame {index}" + (f" ({name})" if name is not None else "")
        self._text(
            f"{what}: {len(estimate.objects)} objects, {len(frame.hypotheses)} hypotheses, "
            f"log P = {estimate.log_prob:.3f}"
            + (" (unchanged scene)" if estimate.unchanged else "")
        )
        for w in estimate.warnings:
            self._text(w, "WARN")
        for r in estimate.rejected:
            self._text(f"rejected {r.id} ({r.class_name}): {r.reason}", "DEBUG")
        for o in estimate.removed:
            self._text(f"removed {o.id} ({o.class_name}): {o.reason}")

    def log_failure(self, index: int, name: str, error: str) -> None:
        """Log a frame that failed (``error``: why) as an error line at ``frame`` = ``index``;
        the scene stays as the last good frame left it."""
        self._set_time(index, None)
        self._text(f"frame {index} ({name}) failed: {error}", "ERROR")

    def _log_camera(self, T_world_cam: np.ndarray | None, camera: Any, depth: Any) -> None:
        """``world/camera``: the pose (axes) and, with ``camera``, a pinhole (the frustum);
        ``world/camera/depth``: ``depth`` (m) as uint16 mm, or cleared without one."""
        rr, rec = self._rr, self._rec
        if depth is not None:
            shape = np.shape(depth)[:2]
            if camera is None or shape != (int(camera.height), int(camera.width)):
                size = None if camera is None else f"{camera.width} x {camera.height}"
                raise RecordingError(f"a depth image of {shape} (H, W) for a camera of {size}")
        if T_world_cam is None:  # nowhere to draw it: the frustum and image need the pose
            camera = depth = None
        else:
            T = np.asarray(T_world_cam, dtype=float)
            rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            rec.log("world/camera", rr.TransformAxes3D(0.1))
        if camera is not None:
            K = [[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy], [0.0, 0.0, 1.0]]
            rec.log(
                "world/camera",
                rr.Pinhole(
                    image_from_camera=K,
                    resolution=[int(camera.width), int(camera.height)],
                    camera_xyz=rr.ViewCoordinates.RDF,  # OpenCV: x right, y down, z forward
                    image_plane_distance=FRUSTUM_DEPTH,
                ),
            )
        if depth is not None:
            rec.log("world/camera/depth", rr.DepthImage(depth_millimetres(depth), meter=1000.0))
            self._depth_shown = True
        elif self._depth_shown:  # no image this frame: not the last one's
            rec.log("world/camera/depth", rr.Clear(recursive=False))
            self._depth_shown = False

    def _log_cloud(self, frame: Frame) -> None:
        """The cloud in three entities (object segments, table, background; module
        docstring); an empty part is logged empty, so the last frame's does not linger."""
        rr = self._rr
        points = np.asarray(frame.points, dtype=np.float32).reshape(-1, 3)
        labels = None if frame.labels is None else np.asarray(frame.labels)
        parts = split_cloud(points, labels, self.max_points)
        objects = parts.objects
        self._rec.log(
            "world/cloud/objects",
            rr.Points3D(
                points[objects],
                colors=label_colours(None if labels is None else labels[objects], len(objects)),
                radii=rr.Radius.ui_points(POINT_RADIUS["objects"]),
            ),
        )
        for part, idx, cls in (
            ("table", parts.table, TABLE_CLASS),
            ("background", parts.background, BACKGROUND_CLASS),
        ):
            self._rec.log(
                f"world/cloud/{part}",
                rr.Points3D(
                    points[idx],
                    class_ids=np.full(len(idx), cls, dtype=np.uint16),
                    radii=rr.Radius.ui_points(POINT_RADIUS[part]),
                ),
            )

    def _log_objects(self, estimate: SceneEstimate, eye: np.ndarray | None) -> None:
        """``world/objects/<id>``: pose, mesh and label of each object (``eye``: the camera
        position, world frame, m, when known); those gone since the last frame cleared."""
        rr, rec = self._rr, self._rec
        present = set()
        for obj in estimate.objects:
            path = f"world/objects/{self._part(obj.id)}"
            present.add(obj.id)
            T = np.asarray(obj.T_world_obj, dtype=float)
            rec.log(path, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
            rgba = (*MODE_COLOURS.get(obj.mode, (200, 200, 200)), OBJECT_ALPHA[obj.ephemeral])
            if obj.id not in self._objects:
                rec.log(f"{path}/mesh", rr.Mesh3D(**self._mesh(obj.class_name), albedo_factor=rgba))
                self._objects.add(obj.id)
            else:
                rec.log(f"{path}/mesh", rr.Mesh3D.from_fields(albedo_factor=rgba))
        self._log_labels(estimate, eye)
        for oid in sorted(self._objects - present):  # removed, or gone without a word
            rec.log(f"world/objects/{self._part(oid)}", rr.Clear(recursive=True))
            self._objects.discard(oid)

    def _log_labels(self, estimate: SceneEstimate, eye: np.ndarray | None) -> None:
        """Each object's one label, its id (``world/objects/<id>/label``, object frame): a
        point of its mode's class above its top (:func:`place_labels`, nearer ``eye`` lower),
        on a thin line down to its top; ``mode`` and ``ephemeral`` as values shown when it is
        selected."""
        rr, rec = self._rr, self._rec
        tops = [
            object_top(
                self.library[o.class_name].mesh.vertices,
                o.T_world_obj,
                self.library[o.class_name].center_of_mass,
            )
            for o in estimate.objects
        ]
        heights = place_labels(np.reshape(tops, (-1, 3)), eye)
        for obj, top, z in zip(estimate.objects, tops, heights, strict=True):
            T = np.asarray(obj.T_world_obj, dtype=float)
            ends = np.array([top, [top[0], top[1], z]])
            local = (ends - T[:3, 3]) @ T[:3, :3]  # world -> object frame
            cls = [mode_class(obj.mode)]
            rec.log(
                f"world/objects/{self._part(obj.id)}/label",
                rr.Points3D(local[1:], class_ids=cls, labels=[str(obj.id)], radii=0.002),
                rr.LineStrips3D([local], class_ids=cls, radii=rr.Radius.ui_points(0.75)),
                rr.AnyValues(mode=str(obj.mode), ephemeral=bool(obj.ephemeral)),
            )

    def _log_instanced(self, root: str, posed: list[tuple[str, np.ndarray]], rgba) -> None:
        """One mesh entity per class under ``root``, drawn at each of its poses."""
        rr, rec = self._rr, self._rec
        by_class: dict[str, list[np.ndarray]] = {}
        for cls, T in posed:
            by_class.setdefault(cls, []).append(np.asarray(T, dtype=float))
        shown = {p for p in self._instanced if p.startswith(root + "/")}
        for cls in sorted(by_class):
            path = f"{root}/{self._part(cls)}"
            poses = np.stack(by_class[cls])
            if path not in self._instanced:
                rec.log(path, rr.Mesh3D(**self._mesh(cls), albedo_factor=rgba))
                self._instanced.add(path)
            rec.log(path, rr.InstancePoses3D(translations=poses[:, :3, 3], mat3x3=poses[:, :3, :3]))
            shown.discard(path)
        for path in sorted(shown):  # no pose of that class in this frame
            rec.log(path, rr.Clear(recursive=False))
            self._instanced.discard(path)

    def _log_support(self, estimate: SceneEstimate) -> None:
        centres = {}
        for obj in estimate.objects:
            com = np.asarray(self.library[obj.class_name].center_of_mass, dtype=float)
            T = np.asarray(obj.T_world_obj, dtype=float)
            centres[obj.id] = T[:3, :3] @ com + T[:3, 3]
        origins, vectors, labels = [], [], []
        for e in estimate.support:
            if e.supported not in centres:
                continue
            top = centres[e.supported]
            if e.supporter in centres:
                base = centres[e.supporter]
            elif e.supporter == "table":
                base = np.array([top[0], top[1], 0.0])
            else:
                continue
            origins.append(base)
            vectors.append(top - base)
            labels.append(f"{e.supporter} -> {e.supported}: {e.fraction:.2f}")
        self._rec.log(
            "world/support",
            self._rr.Arrows3D(
                origins=np.reshape(origins, (-1, 3)),
                vectors=np.reshape(vectors, (-1, 3)),
                labels=labels,
                colors=[SUPPORT_RGB] * len(labels),
                radii=0.003,
                show_labels=False,
            ),
        )

    def _log_terms(self, estimate: SceneEstimate) -> None:
        rr, rec = self._rr, self._rec
        totals = dict.fromkeys(TERMS, 0.0)
        for obj in estimate.objects:
            if obj.terms is None:
                continue
            terms = obj.terms.as_dict()
            base = f"terms/objects/{self._part(obj.id)}"
            if obj.id not in self._styled:  # its term's colour and name, as in the scene's
                self._styled.add(obj.id)
                for t in TERMS:
                    style = rr.SeriesLines(colors=[TERM_COLOURS[t]], names=[t])
                    rec.log(f"{base}/{t}", style, static=True)
            for t in TERMS:
                totals[t] += terms[t]
                rec.log(f"{base}/{t}", rr.Scalars(terms[t]))
        for t in TERMS:
            rec.log(f"terms/scene/{t}", rr.Scalars(totals[t]))
        rec.log("terms/scene/total", rr.Scalars(float(estimate.log_prob)))

    # ------------------------------------------------------------------ end
    def close(self) -> None:
        """Flush and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        if not self._layout_sent:
            self._send_layout(None, None)
        self._rec.flush()
        self._rec.disconnect()
        log.info("%s: recording written", self.path)

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class RunRecording:
    """The recording of an :func:`ssp.pipeline.run.run` (``path`` None: none, and rerun is not
    imported). A recording that fails part way (a full disk, a bug) is logged and stopped; the
    run goes on without it."""

    def __init__(self, path: str | os.PathLike | None, library: Mapping[str, Any]) -> None:
        self.recorder = None if path is None else Recorder(path, library)

    def add(
        self,
        index: int,
        name: str,
        frame_json: Mapping[str, Any],
        perceived: Any = None,
        estimate: SceneEstimate | None = None,
    ) -> None:
        """Log a finished frame: its perceived result (``perceived.frame``, the parser's input;
        ``perceived.camera`` and ``perceived.depth``, the intrinsics and depth image (m), when
        it has them: a frame read from a depth image) and estimate, or
        (``frame_json["status"] == "failed"``) its error."""
        rec = self.recorder
        if rec is None:
            return
        try:
            if frame_json.get("status") == "failed" or estimate is None or perceived is None:
                rec.log_failure(index, name, str(frame_json.get("error", "failed")))
            else:
                rec.log_frame(
                    index,
                    perceived.frame,
                    estimate,
                    name=name,
                    camera=getattr(perceived, "camera", None),
                    depth=getattr(perceived, "depth", None),
                )
        except Exception:
            log.exception("%s: recording failed at frame %s; the run goes on without it", rec.path,
                          name)  # fmt: skip
            self.recorder = None
            try:
                rec.close()
            except Exception:
                log.debug("closing the failed recording", exc_info=True)

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()

    def __enter__(self) -> RunRecording:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------- viewing
def view_command(path: str | os.PathLike, *, web: bool = False) -> list[str]:
    """The command that opens ``path`` in the rerun viewer: the ``rerun`` executable installed
    with the SDK (next to this Python, else on ``PATH``), else ``python -m rerun``; ``web``:
    serve it to a browser instead (``--serve-web``)."""
    here = Path(sys.executable).parent / ("rerun.exe" if os.name == "nt" else "rerun")
    exe = str(here) if here.is_file() else shutil.which("rerun")
    cmd = [exe] if exe else [sys.executable, "-m", "rerun"]
    return [*cmd, *(["--serve-web"] if web else []), str(path)]


def has_display() -> bool:
    """Whether a native window can open here (always on macOS and Windows; on Linux and
    other Unix systems, ``DISPLAY`` or ``WAYLAND_DISPLAY`` must be set)."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def prepare_view(path: str | os.PathLike, *, web: bool = False) -> list[str]:
    """Check that the recording ``path`` can be shown here and return the command that shows
    it (:func:`view_command`).

    Raises:
        RecordingError: ``path`` is not a file, rerun is not installed, or (native viewer) there
            is no display; the message says how to view it elsewhere.
    """
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"{p}: no such recording (write one with ssp run --record {p})")
    require_rerun()
    if not web and not has_display():
        raise RecordingError(
            f"{p}: no display to open the viewer on (DISPLAY and WAYLAND_DISPLAY are unset). "
            f"Copy the file to a machine with a display and run `rerun {p.name}` there, or "
            f"serve it to a browser from here: ssp view --web {p}"
        )
    return view_command(p, web=web)


def view(path: str | os.PathLike, *, web: bool = False) -> list[str]:
    """Open the recording ``path`` in the rerun viewer, a process of its own that outlives this
    one; ``web``: serve it to a browser and wait until the server stops (Ctrl-C). Returns the
    command run. Raises :class:`RecordingError` as :func:`prepare_view`."""
    import subprocess

    cmd = prepare_view(path, web=web)
    log.info("running %s", " ".join(cmd))
    if web:
        subprocess.run(cmd, check=False)
    else:
        subprocess.Popen(cmd, start_new_session=True)
    return cmd
