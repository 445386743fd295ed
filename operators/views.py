"""Views: the scene's cameras as engine cameras, coverage-based view selection, orbit cameras.

Cameras are converted in the splat object's LOCAL frame (its transform, axis conversion included,
is respected) by :mod:`dresg_addon.blender.camera`; the render resolution is the scene's.
"""

import os
from dataclasses import dataclass

import bpy
import numpy as np
from bpy_extras.io_utils import ImportHelper
from mathutils import Matrix

from ..dresg_addon.blender import camera as blender_camera
from ..dresg_addon.util.errors import DresgError
from .splat_object import is_splat_object, object_mode, run_selection, scene_from_object, selection_mask
from .tasks import CancelJobOperator, Job, JobOperator, JobState

ORBIT_COLLECTION = "DReSG Orbit Cameras"
IMPORTED_COLLECTION = "DReSG Cameras"


def scene_cameras(scene) -> list:
    """The scene's camera objects, in a stable (name) order."""
    return sorted((obj for obj in scene.objects if obj.type == "CAMERA"), key=lambda obj: obj.name)


def active_cameras(scene) -> list:
    """The camera objects ticked in the Views list."""
    return [obj for obj in scene_cameras(scene) if obj.dresg_view.use]


SEEN_ENOUGH = 0.95  # below this share of the splats seen by the cameras, the Views panel offers the orbit ring


@dataclass
class ViewPlan:
    """The views a run will paint from, as the Views panel says it and :func:`~.stylize.prepare_job` takes them."""

    camera_objects: list  # the candidate cameras (none: an orbit ring)
    ticked: bool  # the cameras are the ticked ones: all of them are used unless Max Views is lower
    views: int  # the views the run paints from, at most
    line: str  # which views and why, for the panel

    @property
    def orbit(self) -> bool:
        return not self.camera_objects

    @property
    def single(self) -> bool:
        return self.views == 1

    def key(self) -> str:
        """Names the cameras, for what a run or the view selection measured of them (:func:`seen_share`)."""
        return "\n".join(obj.name for obj in self.camera_objects)


def view_plan(scene) -> ViewPlan:
    """The views a run uses: the ticked cameras; with none ticked, the scene's cameras that see the most; with no
    cameras, or Views set to Orbit Ring, an orbit ring (not added to the scene). Max Views caps each (the views
    that see the most are kept)."""
    settings = scene.dresg
    cap = settings.max_views
    cameras, ticked = scene_cameras(scene), active_cameras(scene)

    def capped(count: int) -> int:
        return min(count, cap) if cap else count

    def most(count: int) -> str:
        return f": the {cap} that see the most are used" if cap and cap < count else ""

    if settings.view_source == "ORBIT" or not cameras:
        count = settings.orbit_count
        why = "no cameras" if not cameras else "Orbit Ring chosen"
        return ViewPlan([], False, capped(count), f"{why}: a {count}-view orbit{most(count)}")
    if ticked:
        count = len(ticked)
        only = "only it" if count == 1 else "only they"
        line = f"{count} ticked camera{'s' if count > 1 else ''}: {only} will be used" if not most(count) else ""
        return ViewPlan(ticked, True, capped(count), line or f"{count} ticked cameras{most(count)}")
    count = len(cameras)
    if count == 1:
        return ViewPlan(cameras, False, 1, "1 scene camera: only it will be used")
    if cap and cap < count:
        line = f"{count} scene cameras, none ticked{most(count)}"
    else:
        line = f"{count} scene cameras, none ticked: those that see the splats are used"
    return ViewPlan(cameras, False, capped(count), line)


def seen_share(obj, plan: ViewPlan) -> float | None:
    """The share of the splats the plan's cameras saw, as the last run or view selection on ``obj`` measured it
    with these cameras; None when not measured (or for the orbit ring, which is placed around the splats)."""
    measured = obj.get("dresg_views_seen")
    if plan.orbit or measured is None or measured.get("cameras") != plan.key():
        return None
    return float(measured["seen"])


def record_seen(obj, cameras: str, seen: float) -> None:
    """Keep what a run or the view selection measured (:func:`seen_share`)."""
    obj["dresg_views_seen"] = {"cameras": cameras, "seen": float(seen)}


def camera_params(scene, camera_object) -> blender_camera.BlenderCameraParams:
    data, render = camera_object.data, scene.render
    return blender_camera.BlenderCameraParams(
        lens=data.lens,
        sensor_width=data.sensor_width,
        sensor_height=data.sensor_height,
        sensor_fit=data.sensor_fit,
        shift_x=data.shift_x,
        shift_y=data.shift_y,
        resolution_x=render.resolution_x,
        resolution_y=render.resolution_y,
        resolution_percentage=render.resolution_percentage,
        pixel_aspect_x=render.pixel_aspect_x,
        pixel_aspect_y=render.pixel_aspect_y,
        matrix_world=np.array(camera_object.matrix_world),
        camera_type=data.type,
    )


def engine_cameras(scene, splat_object, camera_objects) -> list:
    """Engine cameras (OpenCV, in the splat object's local frame) for Blender camera objects."""
    matrix = np.array(splat_object.matrix_world)
    cameras = []
    for obj in camera_objects:
        try:
            cameras.append(blender_camera.blender_to_camera(camera_params(scene, obj), matrix, name=obj.name))
        except DresgError as error:
            raise type(error)(f"camera '{obj.name}': {error}") from None
    return cameras


def fit_size(scene) -> tuple[int, int]:
    """The cameras' image size while stylizing, before Fit Scale: the scene's render size, or that aspect
    within View Size when Fit Resolution says so."""
    settings = scene.dresg
    render = scene.render
    width = render.resolution_x * render.resolution_percentage // 100
    height = render.resolution_y * render.resolution_percentage // 100
    if settings.fit_resolution == "PRESET":
        return blender_camera.size_within(width, height, settings.proposal_width, settings.proposal_height)
    return width, height


def fitting_cameras(scene, splat_object, camera_objects) -> list:
    """Engine cameras for camera objects at the size stylizing and view selection use (:func:`fit_size`, then
    Fit Scale)."""
    from ..dresg_addon.method.views import scaled_cameras
    from ..dresg_addon.scene.camera_io import resize_cameras

    cameras = engine_cameras(scene, splat_object, camera_objects)
    width, height = fit_size(scene)
    if cameras and (cameras[0].width, cameras[0].height) != (width, height):
        cameras = resize_cameras(cameras, width=width, height=height)
    return scaled_cameras(cameras, scene.dresg.render_scale)


def add_camera_objects(context, splat_object, cameras, collection_name: str = ORBIT_COLLECTION) -> list:
    """Blender camera objects reproducing engine cameras given in the splat object's local frame."""
    collection = bpy.data.collections.get(collection_name)
    if collection is None:
        collection = bpy.data.collections.new(collection_name)
    if collection.name not in context.scene.collection.children:
        context.scene.collection.children.link(collection)
    matrix = np.array(splat_object.matrix_world)
    corners = np.array([tuple(corner) for corner in splat_object.bound_box])
    objects = []
    for camera in cameras:
        params = blender_camera.camera_to_blender(camera, matrix)
        clip_start, clip_end = blender_camera.clip_distances(camera, corners.min(0), corners.max(0), matrix)
        data = bpy.data.cameras.new(camera.name)
        data.lens, data.sensor_fit = params.lens, params.sensor_fit
        data.sensor_width, data.sensor_height = params.sensor_width, params.sensor_height
        data.shift_x, data.shift_y = params.shift_x, params.shift_y
        data.clip_start, data.clip_end = clip_start, clip_end
        obj = bpy.data.objects.new(camera.name, data)
        obj.matrix_world = Matrix(params.matrix_world.tolist())
        obj.dresg_view.use = True
        collection.objects.link(obj)
        objects.append(obj)
    return objects


def _splat_poll(cls, context) -> bool:
    if not is_splat_object(context.active_object):
        cls.poll_message_set("Select an object imported with Import Gaussian Splats")
        return False
    return True


class SelectionJob(Job):
    """View selection as a :class:`~.tasks.Job`: the splats and cameras are read on the main thread first; the
    worker posts its progress once per camera, and :meth:`~.tasks.Job.poll` (main thread) applies it: the bar's
    fraction, its text, and in background mode (the bpy module, ``blender -b``) one printed line per camera."""

    kind = "select-views"

    def __init__(self, splats, cameras, config, camera_names: list[str], mask=None) -> None:
        super().__init__()
        self.camera_names = camera_names
        self.mask = mask  # [N] bool: count only these splats (the Stylize selection)
        self.text = f"Rendering coverage: 0/{len(cameras)} cameras"
        self.reports: list[tuple[int, int]] = []  # (cameras done, cameras) as they arrived
        self.result = None
        self._inputs = (splats, cameras, config)

    def _update(self, events) -> None:
        for _, (done, total) in events:  # only progress
            self.reports.append((done, total))
            name = self.camera_names[done - 1] if 0 < done <= len(self.camera_names) else ""
            self.fraction = done / max(total, 1)
            self.text = f"Rendering coverage: {done}/{total} cameras" + (f" ({name})" if name else "")
            if self.cancel_requested:
                self.text = "Cancelling..."
            elif bpy.app.background:
                print(f"[select views] {self.text}", flush=True)

    def _on_done(self, result) -> None:
        self.result = result

    def _work(self, post, cancel):  # worker thread: no bpy
        from ..dresg_addon.method.views import select_active_views

        splats, cameras, config = self._inputs
        self._inputs = None
        return select_active_views(
            splats,
            cameras,
            config,
            progress=lambda done, total: post("progress", (done, total)),
            cancel=cancel,
            mask=self.mask,
        )


class DRESG_OT_select_views(JobOperator, bpy.types.Operator):
    """Tick the cameras that together see the most of the splats (up to Max Views), and show each one's share"""

    bl_idname = "dresg.select_views"
    bl_label = "Select Views by Coverage"
    bl_options = {"REGISTER", "UNDO"}

    _interval = 0.2

    @classmethod
    def poll(cls, context):
        from .dependencies import torch_available

        if not _splat_poll(cls, context):
            return False
        if not scene_cameras(context.scene):
            cls.poll_message_set("The scene has no cameras: add orbit cameras first")
            return False
        if not torch_available():
            cls.poll_message_set("PyTorch is not installed (see the add-on preferences)")
            return False
        if SelectionJob.active() is not None:
            cls.poll_message_set("Views are being selected")
            return False
        return True

    def _prepare(self, context) -> SelectionJob:
        obj, scene = context.active_object, context.scene
        objects = scene_cameras(scene)
        cameras = fitting_cameras(scene, obj, objects)
        settings = scene.dresg
        selection = run_selection(obj, settings.selection)
        with object_mode(obj):  # one exit from Edit Mode (and back) for both reads
            mask = selection_mask(obj, selection, settings.selection_group)
            splats = scene_from_object(obj)
        return SelectionJob(splats, cameras, settings.config(), [o.name for o in objects], mask)

    def execute(self, context):
        try:
            job = self._prepare(context)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        return self.run_here(context, job)  # background mode: timers do not fire while a script runs

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        try:
            job = self._prepare(context)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        return self.run_modal(context, job)

    def _finish(self, context, job: SelectionJob):
        if job.state is JobState.CANCELLED:
            self.report({"WARNING"}, "View selection cancelled: the ticks are unchanged")
            return {"CANCELLED"}
        if job.state is JobState.ERROR:
            self.report({"ERROR"}, job.error)
            return {"CANCELLED"}
        by_name = {obj.name: obj for obj in scene_cameras(context.scene)}
        objects = [by_name.get(name) for name in job.camera_names]
        selection = job.result
        picks = {index: order + 1 for order, index in enumerate(selection.indices)}
        for index, camera_object in enumerate(objects):
            if camera_object is None:  # deleted while the selection ran
                continue
            view = camera_object.dresg_view
            view.use = index in picks
            view.pick = picks.get(index, 0)
            view.coverage = float(selection.per_view_coverage[index])
        if is_splat_object(context.active_object):  # what the picked cameras see: the Views panel shows it
            record_seen(context.active_object, view_plan(context.scene).key(), selection.seen)
        total = selection.coverage[-1] if selection.coverage else 0.0
        message = f"Selected {len(picks)} of {len(objects)} views: coverage {100 * total:.2f}% ({selection.reason})"
        blind = [job.camera_names[index] for index in selection.blind]
        if blind:
            self.report({"WARNING"}, f"{message}; {len(blind)} see none of the splats: {', '.join(blind[:5])}")
        else:
            self.report({"INFO"}, message)
        return {"FINISHED"}


class DRESG_OT_cancel_select_views(CancelJobOperator, bpy.types.Operator):
    """Stop the view selection after the current camera; the ticks stay as they were"""

    bl_idname = "dresg.cancel_select_views"
    bl_label = "Cancel View Selection"
    _job_class = SelectionJob


class DRESG_OT_add_orbit_cameras(bpy.types.Operator):
    """Add a ring of cameras around the splats, looking at their centre (for scenes without cameras)"""

    bl_idname = "dresg.add_orbit_cameras"
    bl_label = "Add Orbit Cameras"
    bl_options = {"REGISTER", "UNDO"}

    count: bpy.props.IntProperty(name="Cameras", min=1, max=256, default=12)
    elevation: bpy.props.FloatProperty(name="Elevation", description="Degrees", min=-89.0, max=89.0, default=20.0)
    fov: bpy.props.FloatProperty(
        name="Field of View", description="Horizontal, degrees", min=5.0, max=170.0, default=50.0
    )

    @classmethod
    def poll(cls, context):
        return _splat_poll(cls, context)

    def invoke(self, context, event):
        settings = context.scene.dresg
        self.count, self.elevation, self.fov = settings.orbit_count, settings.orbit_elevation, settings.orbit_fov
        return self.execute(context)

    def execute(self, context):
        from ..dresg_addon.blender.splat_mesh import local_up
        from ..dresg_addon.scene.orbit import orbit_cameras

        obj, scene = context.active_object, context.scene
        width, height = blender_camera.render_size(_render_params(scene))
        try:
            cameras = orbit_cameras(
                scene_from_object(obj),
                self.count,
                width=width,
                height=height,
                fov_deg=self.fov,
                elevation_deg=self.elevation,
                up=local_up(np.array(obj.matrix_world)),
            )
            objects = add_camera_objects(context, obj, cameras)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        if scene.camera is None:
            scene.camera = objects[0]
        self.report({"INFO"}, f"Added {len(objects)} orbit cameras to '{ORBIT_COLLECTION}'")
        return {"FINISHED"}


class DRESG_OT_import_cameras(bpy.types.Operator, ImportHelper):
    """Add the cameras of a capture (cameras.json, COLMAP sparse model, LLFF poses_bounds.npy) around the splats"""

    bl_idname = "dresg.import_cameras"
    bl_label = "Import Cameras"
    bl_options = {"REGISTER", "UNDO"}

    filter_glob: bpy.props.StringProperty(default="*.json;*.bin;*.txt;*.npy", options={"HIDDEN"})

    @classmethod
    def poll(cls, context):
        return _splat_poll(cls, context)

    def execute(self, context):
        from ..dresg_addon.scene.camera_io import load_cameras

        obj, scene = context.active_object, context.scene
        path = bpy.path.abspath(self.filepath)
        try:
            cameras = load_cameras(path)
            objects = add_camera_objects(context, obj, cameras, IMPORTED_COLLECTION)
        except DresgError as error:
            self.report({"ERROR"}, str(error))
            return {"CANCELLED"}
        # Blender cameras share the scene's resolution: take the capture's (the first camera's when they differ).
        sizes = sorted({(camera.width, camera.height) for camera in cameras})
        render = scene.render
        render.resolution_x, render.resolution_y = cameras[0].width, cameras[0].height
        render.resolution_percentage = 100
        if scene.camera is None:
            scene.camera = objects[0]
        message = f"Added {len(objects)} cameras from {os.path.basename(os.path.normpath(path))}"
        message += f"; render size set to {cameras[0].width}x{cameras[0].height}"
        if len(sizes) > 1:
            self.report(
                {"WARNING"}, f"{message} ({len(sizes)} image sizes in the file: intrinsics of the others differ)"
            )
        else:
            self.report({"INFO"}, message)
        return {"FINISHED"}


def _render_params(scene) -> blender_camera.BlenderCameraParams:
    render = scene.render
    return blender_camera.BlenderCameraParams(
        resolution_x=render.resolution_x,
        resolution_y=render.resolution_y,
        resolution_percentage=render.resolution_percentage,
    )


class DRESG_OT_tick_views(bpy.types.Operator):
    """Tick or untick every camera of the Views list"""

    bl_idname = "dresg.tick_views"
    bl_label = "Tick Views"
    bl_options = {"REGISTER", "UNDO", "INTERNAL"}

    use: bpy.props.BoolProperty(name="Use", default=True)

    def execute(self, context):
        for camera_object in scene_cameras(context.scene):
            camera_object.dresg_view.use = self.use
        return {"FINISHED"}


classes = (
    DRESG_OT_select_views,
    DRESG_OT_cancel_select_views,
    DRESG_OT_add_orbit_cameras,
    DRESG_OT_import_cameras,
    DRESG_OT_tick_views,
)
