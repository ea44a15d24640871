"""Calibration of the four-camera rig from ChArUco board images.

The procedure, as on a real line:

1. **Detect** the board's chessboard corners in every image
   (``cv2.aruco.CharucoDetector.detectBoard``) and pair them with their
   positions on the board (``board.matchImagePoints``).
2. **Intrinsics per camera** (``cv2.calibrateCamera``: K and the distortion
   k1, k2, p1, p2, k3) from every view the camera saw, which also gives the
   board's pose in that camera for each view. A corner found more than ten
   times the camera's median error (and 0.5 px) from where that calibration
   puts it is a wrong detection, and is left out before the camera is
   calibrated again: on rendered boards about one corner in 3000 lands
   3-4 px off, next to corners good to 0.05 px, and in a least-squares fit
   that one corner weighs as much as all the others of its view (one such
   corner raised a camera's RMS from 0.07 to 0.11 px over 20 views, from 0.11
   to 0.17 px over 8, where it moved the cameras' centres by up to 0.15 mm).
3. **The rig frame** is fixed by something observable: the *reference view*,
   a board lying flat on the belt at a known place (against a fixture; by
   default centred, its x axis along the belt). Its printed face is z = 0, its
   axes give x and y. Each camera's pose in the rig frame follows from its pose
   of the reference board.
4. **Joint refinement** (bundle adjustment): all intrinsics, all camera poses
   and the board pose of every other view are refined together by minimising
   the reprojection error of every detected corner in every camera
   (``scipy.optimize.least_squares``, sparse finite-difference Jacobian). The
   reference board stays fixed: it is the frame's definition.

Reported: the RMS reprojection error per camera (after refinement), per view,
how many corners and views each camera contributed, and how many corners
it left out.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from .arrays import Image, Transform
from .board import CharucoSpec, board_lying_flat
from .errors import CalibrationError, InvalidInput
from .rig import Camera, Rig, distort_normalized
from .transforms import apply

log = logging.getLogger(__name__)

MIN_CORNERS = 12
"""Fewest corners of a board view that a camera uses (fewer give unstable poses)."""

_N_INTR = 9  # fx, fy, cx, cy, k1, k2, p1, p2, k3
# A corner farther than this from where its camera's own calibration puts it
# is a wrong detection (see the module notes): this many times the camera's
# median error, and at least _OUTLIER_MIN_PX.
_OUTLIER_FACTOR = 10.0
_OUTLIER_MIN_PX = 0.5


@dataclass(frozen=True, eq=False)
class Detection:
    """Board corners found in one image.

    Attributes
    ----------
    ids : (N,) int32
        ChArUco corner ids.
    object_points : (N, 3) float64, mm, board frame
    image_points : (N, 2) float64, pixels
    """

    ids: npt.NDArray[np.int32]
    object_points: npt.NDArray[np.float64]
    image_points: npt.NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Calibration:
    """The result of :func:`calibrate`.

    Attributes
    ----------
    rig : Rig
        The calibrated rig (cameras estimated; projector and conveyor from
        the template, since boards cannot observe them).
    rms_px : tuple of float
        RMS reprojection error per camera after the joint refinement, pixels.
    initial_rms_px : tuple of float
        RMS per camera of the per-camera ``cv2.calibrateCamera``.
    view_rms_px : (V, 4) float64
        RMS per view and camera after refinement (NaN where not used).
    corners : tuple of int
        Corners used per camera.
    rejected : tuple of int
        Corners left out per camera as wrong detections (step 2 of the module notes).
    views_used : tuple of int
        Views used per camera.
    T_rig_boards : (V, 4, 4) float64
        Estimated board pose of every view in the rig frame (NaN where no
        camera saw it).
    """

    rig: Rig
    rms_px: tuple[float, ...]
    initial_rms_px: tuple[float, ...]
    view_rms_px: npt.NDArray[np.float64]
    corners: tuple[int, ...]
    rejected: tuple[int, ...]
    views_used: tuple[int, ...]
    T_rig_boards: npt.NDArray[np.float64]

    def summary(self) -> str:
        """A few lines for people."""
        lines = [f"rig {self.rig.id}: {self.rig.source}"]
        for i, cam in enumerate(self.rig.cameras):
            lines.append(
                f"  {cam.name}: RMS {self.rms_px[i]:.3f} px "
                f"(per camera {self.initial_rms_px[i]:.3f}), "
                f"{self.corners[i]} corners in {self.views_used[i]} views"
                + (f" ({self.rejected[i]} left out)" if self.rejected[i] else "")
                + ", "
                f"centre {np.round(cam.centre, 2).tolist()} mm"
            )
        return "\n".join(lines)


def make_detector(board: CharucoSpec) -> cv2.aruco.CharucoDetector:
    """A ChArUco detector for ``board`` with sub-pixel marker refinement."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    charuco = cv2.aruco.CharucoParameters()
    charuco.tryRefineMarkers = True
    return cv2.aruco.CharucoDetector(board.make_board(), charuco, params)


def detect_board(
    image: Image, board: CharucoSpec, detector: cv2.aruco.CharucoDetector | None = None
) -> Detection | None:
    """Find the ChArUco corners in one image.

    Parameters
    ----------
    image : (H, W) uint8
    board : CharucoSpec
    detector : optional, from :func:`make_detector` (reused across images)

    Returns
    -------
    Detection or None
        None when fewer than :data:`MIN_CORNERS` corners were found.
    """
    img = _check_image(image, "image")
    det = detector if detector is not None else make_detector(board)
    corners, ids, _, _ = det.detectBoard(img)
    if ids is None or len(ids) < MIN_CORNERS:
        return None
    obj, imgp = det.getBoard().matchImagePoints(corners, ids)  # type: ignore[call-overload]
    if obj is None or len(obj) < MIN_CORNERS:
        return None
    return Detection(
        ids.reshape(-1).astype(np.int32),
        obj.reshape(-1, 3).astype(np.float64),
        imgp.reshape(-1, 2).astype(np.float64),
    )


def calibration_poses(
    n_views: int,
    *,
    seed: int = 0,
    board: CharucoSpec | None = None,
    reference: Transform | None = None,
) -> list[Transform]:
    """Board poses that calibrate the rig well: the reference view, then tilted views.

    The first pose is ``reference`` (default: the board flat on the belt,
    centred, x along the belt). The others put the board anywhere in the
    measurement volume, tilted by 15-40° about a random horizontal axis
    (tilts are what make focal length and distortion observable), turned
    about z by up to ±40°, and lifted so that it stays above the belt.

    Returns
    -------
    list of (4, 4) float64
        T_rig_board for each view.
    """
    spec = board if board is not None else CharucoSpec()
    if n_views < 4:
        raise InvalidInput("calibration needs at least 4 views (the reference and 3 tilted ones)")
    rng = np.random.default_rng(seed)
    poses = [reference if reference is not None else board_lying_flat(spec)]
    w, h = spec.size_mm
    rim = spec.rim_mm
    outline = np.array(
        [[-rim, -rim, 0.0], [w + rim, -rim, 0.0], [w + rim, h + rim, 0.0], [-rim, h + rim, 0.0]]
    )
    while len(poses) < n_views:
        centre = np.array([rng.uniform(-200, 200), rng.uniform(-110, 110), 0.0])
        yaw = rng.uniform(-40, 40)
        axis_angle = rng.uniform(0, 2 * np.pi)
        tilt = np.deg2rad(rng.uniform(15, 40))
        base = board_lying_flat(spec, (0.0, 0.0), yaw)
        R_tilt = Rotation.from_rotvec(
            tilt * np.array([np.cos(axis_angle), np.sin(axis_angle), 0.0])
        ).as_matrix()
        T = np.eye(4)
        T[:3, :3] = R_tilt @ base[:3, :3]
        T[:3, 3] = R_tilt @ base[:3, 3]
        corners = apply(T, outline)
        lift = rng.uniform(5, 90) - corners[:, 2].min()
        T[:3, 3] += centre + np.array([0.0, 0.0, lift])
        corners = apply(T, outline)
        if corners[:, 2].max() > 260:  # keep the board within the cameras' depth of field
            continue
        poses.append(T)
    return poses


def render_calibration_views(
    rig: Rig,
    n_views: int,
    *,
    seed: int = 0,
    board: CharucoSpec | None = None,
    reference: Transform | None = None,
    supersample: int = 5,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[list[list[Image]], list[Transform]]:
    """Render the board in :func:`calibration_poses` with the simulator.

    ``supersample`` is passed to :func:`inspection.simulate.simulate_board`;
    ``progress(fraction, stage)`` is called after each view.

    Returns
    -------
    views : list (n_views) of list of four (H, W) uint8
    poses : list of (4, 4) float64, the true T_rig_board of each view
    """
    from .simulate import simulate_board  # the simulator only where boards are rendered

    spec = board if board is not None else CharucoSpec()
    poses = calibration_poses(n_views, seed=seed, board=spec, reference=reference)
    views = []
    for k, T in enumerate(poses):
        views.append(simulate_board(rig, T, spec, seed=seed * 1000 + k, supersample=supersample))
        if progress is not None:
            progress((k + 1) / len(poses), "rendering the board")
    return views, poses


def calibrate(
    views: Sequence[Sequence[Image]],
    *,
    board: CharucoSpec | None = None,
    T_rig_board_ref: Transform | None = None,
    reference_view: int = 0,
    template: Rig | None = None,
    source: str | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> Calibration:
    """Calibrate the four cameras of the rig from ChArUco board images.

    Parameters
    ----------
    views : sequence of V sequences of four (H, W) uint8
        ``views[v][c]`` is camera c's image of board view v (cameras in the
        order of ``template.cameras``).
    board : CharucoSpec, optional
        The board (default :class:`CharucoSpec` ()).
    T_rig_board_ref : (4, 4) float64, optional
        Where the reference board lies in the rig frame (default: flat on the
        belt, centred, x along the belt: :func:`inspection.board.board_lying_flat`).
    reference_view : int
        Index of the reference view; every camera must see it.
    template : Rig, optional
        Names and image sizes of the cameras, projector, conveyor and stereo
        pairs (default :meth:`Rig.nominal`; boards do not observe them).
    source : str, optional
        Recorded in the rig file (default: a summary of the calibration).
    progress : callable, optional
        ``progress(fraction, stage)``, called as the board is detected in
        each view, each camera is calibrated and the rig is refined.

    Returns
    -------
    Calibration

    Raises
    ------
    InvalidInput
        Malformed views (wrong count, shape, dtype) or a bad reference.
    CalibrationError
        A camera saw too few boards, or a camera missed the reference view.
    """
    # OpenCV's parallel loops sum in a varying order; one thread makes the
    # result (and so the calibration id) the same bit for bit on every run.
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        return _calibrate(views, board, T_rig_board_ref, reference_view, template, source, progress)
    finally:
        cv2.setNumThreads(threads)


def _calibrate(
    views, board, T_rig_board_ref, reference_view, template, source, progress
) -> Calibration:
    report = progress if progress is not None else (lambda fraction, stage: None)
    spec = board if board is not None else CharucoSpec()
    tmpl = template if template is not None else Rig.nominal()
    n_cams = len(tmpl.cameras)
    if len(views) < 4:
        raise InvalidInput(f"calibration needs at least 4 views, got {len(views)}")
    if not 0 <= reference_view < len(views):
        raise InvalidInput(f"reference_view {reference_view} is not one of the {len(views)} views")
    T_ref = (
        board_lying_flat(spec)
        if T_rig_board_ref is None
        else np.asarray(T_rig_board_ref, np.float64)
    )
    if T_ref.shape != (4, 4) or not np.all(np.isfinite(T_ref)):
        raise InvalidInput("T_rig_board_ref must be a finite (4, 4) transform")

    # 1. detection
    detector = make_detector(spec)
    dets: list[list[Detection | None]] = []
    for v, view in enumerate(views):
        if len(view) != n_cams:
            raise InvalidInput(f"view {v} has {len(view)} images, the rig has {n_cams} cameras")
        row = []
        for c, image in enumerate(view):
            img = _check_image(image, f"view {v} camera {c}")
            cam = tmpl.cameras[c]
            if img.shape != cam.shape:
                raise InvalidInput(
                    f"view {v} camera {c}: image is {img.shape}, the camera's is {cam.shape}"
                )
            row.append(detect_board(img, spec, detector))
        dets.append(row)
        report(0.6 * (v + 1) / len(views), "detecting the board")

    # 2. intrinsics per camera
    intr = []
    poses_cam: list[dict[int, Transform]] = []
    initial_rms = []
    rejected: list[int] = []
    for c, cam in enumerate(tmpl.cameras):
        used = [v for v in range(len(views)) if dets[v][c] is not None]
        if len(used) < 4:
            raise CalibrationError(
                f"camera {cam.name} found the board in only {len(used)} views (need 4)"
            )
        if dets[reference_view][c] is None:
            raise CalibrationError(
                f"camera {cam.name} did not find the board in the reference view {reference_view}"
            )
        found = [d for v in used if (d := dets[v][c]) is not None]
        rms, K, dist, rvecs, tvecs = _calibrate_camera(found, cam.size)
        kept = _drop_outliers(found, K, dist, rvecs, tvecs)
        rejected.append(sum(len(d.ids) for d in found) - sum(len(d.ids) for d in kept))
        if rejected[-1]:
            # A view left with too few good corners is not used by this camera.
            for v, d in zip(used, kept, strict=True):
                dets[v][c] = d if len(d.ids) >= MIN_CORNERS else None
            used = [v for v in used if dets[v][c] is not None]
            if len(used) < 4 or dets[reference_view][c] is None:
                raise CalibrationError(
                    f"camera {cam.name}: after leaving out {rejected[-1]} wrongly detected "
                    f"corners, {len(used)} views are left"
                    + ("" if dets[reference_view][c] is not None else ", not the reference view")
                )
            kept = [d for v in used if (d := dets[v][c]) is not None]
            rms, K, dist, rvecs, tvecs = _calibrate_camera(kept, cam.size)
            log.info("camera %s: %d wrongly detected corner(s) left out", cam.name, rejected[-1])
        initial_rms.append(float(rms))
        intr.append((K, dist.reshape(-1)[:5]))
        poses = {}
        for v, rv, tv in zip(used, rvecs, tvecs, strict=True):
            T = np.eye(4)
            T[:3, :3] = cv2.Rodrigues(rv)[0]
            T[:3, 3] = tv.reshape(3)
            poses[v] = T
        poses_cam.append(poses)
        log.debug("camera %s: calibrateCamera RMS %.3f px over %d views", cam.name, rms, len(used))

    report(0.8, "placing the cameras")
    # 3. the rig frame from the reference board: T_cam_rig = T_cam_board @ T_board_rig
    T_cam_rig = [poses_cam[c][reference_view] @ np.linalg.inv(T_ref) for c in range(n_cams)]
    T_rig_board = np.full((len(views), 4, 4), np.nan)
    for v in range(len(views)):
        if v == reference_view:
            T_rig_board[v] = T_ref
            continue
        seen = [c for c in range(n_cams) if v in poses_cam[c]]
        if seen:
            c = seen[0]
            T_rig_board[v] = np.linalg.inv(T_cam_rig[c]) @ poses_cam[c][v]

    # 4. joint refinement
    report(0.85, "refining the rig jointly")
    cams, T_rig_board, rms, view_rms, counts = _bundle_adjust(
        tmpl, intr, T_cam_rig, T_rig_board, dets, reference_view
    )
    views_used = tuple(
        sum(1 for v in range(len(views)) if dets[v][c] is not None) for c in range(n_cams)
    )
    text = (
        source
        if source is not None
        else (
            f"calibrated from {len(views)} ChArUco views "
            f"({spec.squares_x}x{spec.squares_y} x {spec.square_mm:g} mm), "
            f"reprojection RMS {', '.join(f'{r:.3f}' for r in rms)} px"
        )
    )
    rig = Rig(
        tuple(cams),
        tmpl.projector,
        tmpl.conveyor,
        tmpl.stereo_pairs,
        tmpl.ring_pairs,
        text,
        tuple(round(r, 4) for r in rms),
    )
    report(1.0, "calibrated")
    return Calibration(
        rig,
        tuple(rms),
        tuple(initial_rms),
        view_rms,
        tuple(counts),
        tuple(rejected),
        views_used,
        T_rig_board,
    )


def _calibrate_camera(found, size):
    """``cv2.calibrateCamera`` of one camera from its detections ``found`` (one per view)."""
    obj = [d.object_points.astype(np.float32) for d in found]
    img_pts = [d.image_points.astype(np.float32) for d in found]
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    return cv2.calibrateCamera(obj, img_pts, size, None, None, criteria=crit)


def _drop_outliers(found, K, dist, rvecs, tvecs):
    """One camera's detections ``found`` without the corners that its calibration
    (K, dist and the board poses) puts far from where they were found."""
    errors = []
    for d, rv, tv in zip(found, rvecs, tvecs, strict=True):
        uv, _ = cv2.projectPoints(d.object_points, rv, tv, K, dist)
        errors.append(np.linalg.norm(uv.reshape(-1, 2) - d.image_points, axis=1))
    limit = max(_OUTLIER_MIN_PX, _OUTLIER_FACTOR * float(np.median(np.concatenate(errors))))
    kept = []
    for d, e in zip(found, errors, strict=True):
        ok = e <= limit
        kept.append(
            d if ok.all() else Detection(d.ids[ok], d.object_points[ok], d.image_points[ok])
        )
    return kept


def _bundle_adjust(tmpl, intr, T_cam_rig, T_rig_board, dets, ref):
    """Refine intrinsics, camera poses and board poses together (reference board fixed)."""
    n_cams = len(tmpl.cameras)
    n_views = len(dets)
    free_views = [v for v in range(n_views) if v != ref and np.all(np.isfinite(T_rig_board[v]))]
    view_slot = {v: k for k, v in enumerate(free_views)}
    cam_block = _N_INTR + 6
    n_params = n_cams * cam_block + 6 * len(free_views)

    x0 = np.empty(n_params)
    for c in range(n_cams):
        K, dist = intr[c]
        b = c * cam_block
        x0[b : b + 4] = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        x0[b + 4 : b + 9] = dist
        x0[b + 9 : b + 12] = Rotation.from_matrix(T_cam_rig[c][:3, :3]).as_rotvec()
        x0[b + 12 : b + 15] = T_cam_rig[c][:3, 3]
    vb = n_cams * cam_block
    for k, v in enumerate(free_views):
        x0[vb + 6 * k : vb + 6 * k + 3] = Rotation.from_matrix(T_rig_board[v][:3, :3]).as_rotvec()
        x0[vb + 6 * k + 3 : vb + 6 * k + 6] = T_rig_board[v][:3, 3]

    # Observations, flattened: camera, view slot (-1: reference), board point, pixel.
    obs_cam, obs_view, obs_obj, obs_img, obs_v = [], [], [], [], []
    for v in range(n_views):
        if v != ref and v not in view_slot:
            continue
        for c in range(n_cams):
            d = dets[v][c]
            if d is None:
                continue
            n = len(d.ids)
            obs_cam.append(np.full(n, c))
            obs_view.append(np.full(n, view_slot.get(v, -1)))
            obs_v.append(np.full(n, v))
            obs_obj.append(d.object_points)
            obs_img.append(d.image_points)
    cam_idx = np.concatenate(obs_cam)
    view_idx = np.concatenate(obs_view)
    v_idx = np.concatenate(obs_v)
    obj = np.concatenate(obs_obj)
    img = np.concatenate(obs_img)
    R_ref = T_rig_board[ref][:3, :3]
    t_ref = T_rig_board[ref][:3, 3]
    n_obs = len(obj)

    def residuals(x: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
        cam_p = x[: n_cams * cam_block].reshape(n_cams, cam_block)
        view_p = x[vb:].reshape(-1, 6)
        # board -> rig
        Xr = np.empty_like(obj)
        is_ref = view_idx < 0
        Xr[is_ref] = obj[is_ref] @ R_ref.T + t_ref
        if len(view_p):
            R_v = Rotation.from_rotvec(view_p[:, :3]).as_matrix()
            sel = ~is_ref
            vi = view_idx[sel]
            Xr[sel] = np.einsum("nij,nj->ni", R_v[vi], obj[sel]) + view_p[vi, 3:]
        # rig -> camera -> pixels
        R_c = Rotation.from_rotvec(cam_p[:, 9:12]).as_matrix()
        Xc = np.einsum("nij,nj->ni", R_c[cam_idx], Xr) + cam_p[cam_idx, 12:15]
        xy = Xc[:, :2] / Xc[:, 2:3]
        out = np.empty((n_obs, 2))
        for c in range(n_cams):
            m = cam_idx == c
            xd = distort_normalized(xy[m], cam_p[c, 4:9])
            out[m, 0] = cam_p[c, 0] * xd[:, 0] + cam_p[c, 2] - img[m, 0]
            out[m, 1] = cam_p[c, 1] * xd[:, 1] + cam_p[c, 3] - img[m, 1]
        return out.ravel()

    sparsity = lil_matrix((2 * n_obs, n_params), dtype=np.int8)
    rows = np.arange(n_obs)
    for k in range(cam_block):
        cols = cam_idx * cam_block + k
        sparsity[2 * rows, cols] = 1
        sparsity[2 * rows + 1, cols] = 1
    free = view_idx >= 0
    for k in range(6):
        cols = vb + 6 * view_idx[free] + k
        sparsity[2 * rows[free], cols] = 1
        sparsity[2 * rows[free] + 1, cols] = 1
    res = least_squares(
        residuals,
        x0,
        jac_sparsity=sparsity.tocsr(),
        method="trf",
        x_scale="jac",
        # From calibrateCamera's start the cost settles within ~20 evaluations;
        # after that the finite-difference steps only crawl (relative cost
        # changes < 1e-7 move the RMS by < 1e-7 px): stop there.
        xtol=1e-10,
        ftol=1e-7,
        gtol=1e-10,
        max_nfev=100,
    )
    log.debug(
        "bundle adjustment: %s, cost %.4g -> %.4g",
        res.message,
        0.5 * np.sum(residuals(x0) ** 2),
        res.cost,
    )
    r = res.fun.reshape(-1, 2)
    sq = (r**2).sum(axis=1)

    cams = []
    rms = []
    counts = []
    view_rms = np.full((n_views, n_cams), np.nan)
    for c, tcam in enumerate(tmpl.cameras):
        p = res.x[c * cam_block : (c + 1) * cam_block]
        K = np.array([[p[0], 0.0, p[2]], [0.0, p[1], p[3]], [0.0, 0.0, 1.0]])
        R = Rotation.from_rotvec(p[9:12]).as_matrix()
        cams.append(
            Camera(tcam.name, tcam.width, tcam.height, K, p[4:9].copy(), R, p[12:15].copy())
        )
        m = cam_idx == c
        rms.append(float(np.sqrt(sq[m].mean())))
        counts.append(int(m.sum()))
        for v in np.unique(v_idx[m]):
            mv = m & (v_idx == v)
            view_rms[v, c] = float(np.sqrt(sq[mv].mean()))
    T_out = T_rig_board.copy()
    for k, v in enumerate(free_views):
        q = res.x[vb + 6 * k : vb + 6 * k + 6]
        T_out[v] = np.eye(4)
        T_out[v][:3, :3] = Rotation.from_rotvec(q[:3]).as_matrix()
        T_out[v][:3, 3] = q[3:]
    return cams, T_out, rms, view_rms, counts


def _check_image(image: object, what: str) -> Image:
    arr = np.asarray(image)
    if arr.dtype != np.uint8:
        raise InvalidInput(f"{what}: images must be uint8, got {arr.dtype}")
    if arr.ndim != 2:
        raise InvalidInput(f"{what}: images must be grey (H, W), got shape {arr.shape}")
    return arr


def centre_errors(estimated: Rig, truth: Rig) -> npt.NDArray[np.float64]:
    """Distances (mm) of the estimated camera centres from the true ones after one rigid alignment.

    The estimated rig frame is defined by the reference board, which is itself
    measured with some error; a single rigid transform (Kabsch over the four
    centres) takes that out before the centres are compared.

    Returns
    -------
    (4,) float64, mm
    """
    from .rig import rigid_align

    est = np.array([c.centre for c in estimated.cameras])
    tru = np.array([c.centre for c in truth.cameras])
    T = rigid_align(est, tru)
    return np.linalg.norm(apply(T, est) - tru, axis=1)


def stereo_errors(
    estimated: Rig, truth: Rig, *, steps: tuple[int, int, int] = (8, 6, 5)
) -> dict[tuple[int, int], tuple[float, float]]:
    """What calibration error costs a measurement: triangulation errors over the volume.

    Points on a grid filling the measurement volume are projected with the
    true cameras and triangulated (midpoint of the two rays) with the
    estimated ones, for each stereo pair of ``estimated``; the errors are
    taken after one rigid alignment of all points (a rigid offset of the
    rig frame is taken out by registration to the CAD anyway).

    Returns
    -------
    dict
        ``(a, b) -> (rms_mm, max_mm)`` per stereo pair.
    """
    from .rig import VOLUME_MM, rigid_align

    vx, vy, vz = VOLUME_MM
    axes = [
        np.linspace(-0.45 * vx, 0.45 * vx, steps[0]),
        np.linspace(-0.45 * vy, 0.45 * vy, steps[1]),
        np.linspace(0.0, vz, steps[2]),
    ]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    out = {}
    for a, b in estimated.stereo_pairs:
        oa, da = estimated.cameras[a].rays(truth.cameras[a].project(grid))
        ob, db = estimated.cameras[b].rays(truth.cameras[b].project(grid))
        # closest points of the two rays (midpoint triangulation)
        w0 = oa - ob
        aa = (da * da).sum(1)
        bb = (da * db).sum(1)
        cc = (db * db).sum(1)
        dd = (da * w0).sum(1)
        ee = (db * w0).sum(1)
        den = aa * cc - bb * bb
        s = (bb * ee - cc * dd) / den
        t = (aa * ee - bb * dd) / den
        X = 0.5 * ((oa + s[:, None] * da) + (ob + t[:, None] * db))
        T = rigid_align(X, grid)
        err = np.linalg.norm(apply(T, X) - grid, axis=1)
        out[(a, b)] = (float(np.sqrt(np.mean(err**2))), float(err.max()))
    return out
