"""Every file and folder name in a run directory, in one place (docs/run-directory.md).

A run is its **capture** at the top (``profile.toml``, ``calibration.json``, ``manifest.json``,
``events.jsonl``, ``frames/``, ``transillumination/``, ``live/``) and **generations** of
products under ``gen/NNN/`` (``views/``, ``cloud.ply``, ``report.json``, ``previews/``,
``surface.ply``, ``volume.vtu``, ``meshes/``, ``normalize/``, exports), published through the
link ``current``. Modules ask :class:`RunLayout` for a name instead of spelling it, so that
the on-disk contract is written once. Names are relative POSIX paths, for
:meth:`~dotshell.run.store.RunStore.path` (which joins them to the run or generation).
"""

from __future__ import annotations


class RunLayout:
    """The names of a run directory (class attributes and static methods; no state)."""

    # ---- the capture (written once, never changed by re-processing) ----
    PROFILE = "profile.toml"  #: the exact, validated profile of the scan
    CALIBRATION = "calibration.json"  #: the capture's calibration (each generation has a copy)
    MANIFEST = "manifest.json"  #: status, views, frame names, devices, jobs
    EVENTS = "events.jsonl"  #: one event per line, appended
    LOCK = ".lock"  #: the writer's OS file lock
    RESERVE = ".reserve"  #: space held back while a job runs
    FRAMES = "frames"  #: raw captures, one TIFF stack per view
    TRANSILLUMINATION = "transillumination"  #: trans-illumination, dark and flat frames
    LIVE = "live"  #: a session's live preview of the latest view
    LATEST_FRAME = "live/latest_frame.png"  #: the first frame of the latest captured view
    SERVER_LOG = "server.log"  #: the rig server's log, when a run is written by one
    SNAPSHOTS = "snapshots"  #: a session's saved snapshots
    TRUTH = "truth.json"  #: a simulated rig's ground truth, index (dotshell.run.truth)
    TRUTH_DIR = "truth"  #: its arrays

    # ---- generations of products ----
    GEN = "gen"  #: gen/NNN/, one per processing job
    CURRENT = "current"  #: link to the published generation
    PRODUCTS = "products.json"  #: a generation's product → files listing, written last
    REPORT = "report.json"  #: figures of the generation
    VIEWS = "views"  #: per-view clouds and records
    CLOUD = "cloud.ply"  #: all views merged (mm)
    PREVIEWS = "previews"  #: PNG previews
    SURFACE = "surface.ply"  #: the surface mesh (mm)
    VOLUME = "volume.vtu"  #: the volume mesh (mm)
    OPTODES = "optodes.json"  #: sources and detectors on the mesh
    FORWARD = "forward.vtu"  #: the forward solution
    MESHES = "meshes"  #: further node distances: meshes/<d>mm/
    NORMALIZE = "normalize"  #: the normalization's outputs
    VIEW_GLOB = "view_*"  #: matches every per-view name (glob)

    @staticmethod
    def view_stem(view: int) -> str:
        """``view_NNN``: the stem of every per-view name (0-based view index)."""
        return f"view_{view:03d}"

    @staticmethod
    def view_index(stem: str) -> int:
        """The view index of a ``view_NNN`` stem (the inverse of :meth:`view_stem`)."""
        return int(stem.split("_")[1])

    @staticmethod
    def generation_dir(number: int) -> str:
        """``gen/NNN``: a generation's folder."""
        return f"{RunLayout.GEN}/{number:03d}"

    @staticmethod
    def frame_stack(view: int) -> str:
        """``frames/view_NNN.tif``: a view's raw captures (frame_format tiff-stack/1)."""
        return f"{RunLayout.FRAMES}/{RunLayout.view_stem(view)}.tif"

    @staticmethod
    def frame_folder(view: int) -> str:
        """``frames/view_NNN``: a view's frame metadata, and its PNG frames in runs made
        before TIFF stacks."""
        return f"{RunLayout.FRAMES}/{RunLayout.view_stem(view)}"

    @staticmethod
    def frame_info(view: int) -> str:
        """``frames/view_NNN/frame_info.json``: a view's frame metadata (cameras that report
        it)."""
        return f"{RunLayout.frame_folder(view)}/frame_info.json"

    @staticmethod
    def png_frame(index: int, name: str) -> str:
        """``III_NAME.png``: a frame in a view's folder of PNG frames (runs before TIFF
        stacks, and ``dotshell frames --png``); ``index`` is its place in the sequence."""
        return f"{index:03d}_{name}.png"

    @staticmethod
    def set_aside(view: int, k: int) -> str:
        """``frames/view_NNN.partial-K``: the K-th set of an unfinished view's frames moved
        out of the way before the view is captured again (+ ``.tif`` for the stack)."""
        return f"{RunLayout.frame_folder(view)}.partial-{k}"

    @staticmethod
    def view_cloud(view: int) -> str:
        """``views/view_NNN.ply``: the view's points in the sample frame (mm)."""
        return f"{RunLayout.VIEWS}/{RunLayout.view_stem(view)}.ply"

    @staticmethod
    def view_record(view: int) -> str:
        """``views/view_NNN.json``: the view's report record."""
        return f"{RunLayout.VIEWS}/{RunLayout.view_stem(view)}.json"

    @staticmethod
    def preview(name: str) -> str:
        """``previews/NAME.png``."""
        return f"{RunLayout.PREVIEWS}/{name}.png"

    @staticmethod
    def view_preview(kind: str, view: int) -> str:
        """``previews/KIND_view_NNN.png`` (kind ``frame`` or ``columns``)."""
        return RunLayout.preview(f"{kind}_{RunLayout.view_stem(view)}")

    @staticmethod
    def trans_frame(name: str, view: int | None = None) -> str:
        """``transillumination/view_NNN/NAME.png``, or ``transillumination/NAME.png`` for the
        run's flat-field frames (``view`` None)."""
        if view is None:
            return f"{RunLayout.TRANSILLUMINATION}/{name}.png"
        return f"{RunLayout.TRANSILLUMINATION}/{RunLayout.view_stem(view)}/{name}.png"

    @staticmethod
    def mesh_dir_name(node_distance_mm: float) -> str:
        """``<d>mm``: names the meshes at a node distance (mm): their folder, preview suffix."""
        return f"{node_distance_mm:g}mm"

    @staticmethod
    def mesh_dir(node_distance_mm: float) -> str:
        """``meshes/<d>mm``: the meshes at a further node distance (mm)."""
        return f"{RunLayout.MESHES}/{RunLayout.mesh_dir_name(node_distance_mm)}"

    @staticmethod
    def normalize_file(name: str) -> str:
        """``normalize/NAME``."""
        return f"{RunLayout.NORMALIZE}/{name}"
