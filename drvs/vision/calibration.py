"""A camera's pose in ``map`` from one image and four or more floor points at known positions.

The points are AprilTags (tag36h11) lying flat on the floor, found with OpenCV's aruco
module, or pixel/map pairs picked by hand (OpenCV pixel coordinates); ``cv2.solvePnP``
gives the pose, which :class:`Calibration` prints for tf and a world file. How to use it:
docs/tutorials/your-camera.md; how tags are located: docs/design.md ("Vision systems").
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import yaml
from numpy.typing import ArrayLike

MIN_POINTS = 4
TAG_FAMILY = 'tag36h11'
TAG_IDS = 587
"""tag36h11 has ids 0 .. 586."""
COLLINEAR_RATIO = 1e-3
"""Floor points whose spread across their main line is below this fraction of the spread along it
are on one line: every camera on a circle around that line sees them the same way."""
DISTORTION_MODELS = ('plumb_bob', 'rational_polynomial')
STATIC_TRANSFORM_PUBLISHER = '/usr/lib/tf2_ros/static_transform_publisher'
"""tf2's static_transform_publisher as Debian's tf2-tools installs it (``rosrun tf2_ros
static_transform_publisher`` where rosbash and catkin are installed)."""


class CalibrationError(ValueError):
    """Input that gives no pose; the message names the problem and what to do."""


# -- parsing -----------------------------------------------------------------------------------
def _numbers(text: str, count: int, what: str, example: str, whole: str | None = None) -> tuple[float, ...]:
    """``count`` comma-separated finite numbers; the error quotes ``whole`` (default ``text``)."""
    try:
        values = tuple(float(part) for part in text.split(','))
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise CalibrationError(f'{whole if whole is not None else text!r}: expected {what}, e.g. {example}')
    return values


@dataclass(frozen=True)
class TagSpec:
    """``--tag ID:X,Y``: tag ``id`` lies with its centre at (x, y) on the floor of ``map``."""

    id: int
    floor: tuple[float, float]


@dataclass(frozen=True)
class FloorPoint:
    """One correspondence: ``pixel`` (OpenCV coordinates) shows the floor point (x, y, 0) of ``map``."""

    label: str
    pixel: tuple[float, float]
    floor: tuple[float, float]


def parse_tag(text: str) -> TagSpec:
    """``'3:1.5,2.0'`` -> tag 3 at (1.5, 2.0).

    >>> parse_tag('3:1.5,2')
    TagSpec(id=3, floor=(1.5, 2.0))
    """
    what = 'ID:X,Y (a tag36h11 id and the map position of its centre, metres)'
    tag_id, _, floor = text.partition(':')
    if not tag_id.strip().isdigit():
        raise CalibrationError(f'{text!r}: expected {what}, e.g. 3:1.5,2.0')
    if int(tag_id) >= TAG_IDS:
        raise CalibrationError(f'{text!r}: tag36h11 ids are 0 to {TAG_IDS - 1}')
    x, y = _numbers(floor, 2, what, '3:1.5,2.0', text)
    return TagSpec(int(tag_id), (x, y))


def parse_point(text: str, index: int = 1) -> FloorPoint:
    """``'412.5,300:1.0,2.0'`` -> pixel (412.5, 300) shows map (1.0, 2.0); labelled ``point INDEX``.

    >>> parse_point('412.5,300:1,2', 2)
    FloorPoint(label='point 2', pixel=(412.5, 300.0), floor=(1.0, 2.0))
    """
    what = 'U,V:X,Y (OpenCV pixel, then map position in metres)'
    pixel, _, floor = text.partition(':')
    example = '412.5,300:1.0,2.0'
    u, v = _numbers(pixel, 2, what, example, text)
    x, y = _numbers(floor, 2, what, example, text)
    return FloorPoint(f'point {index}', (u, v), (x, y))


def parse_distortion(text: str) -> tuple[float, ...]:
    """``'k1,k2,p1,p2,k3'`` -> the 5 plumb_bob coefficients."""
    return _numbers(text, 5, '5 comma-separated numbers k1,k2,p1,p2,k3', '-0.2,0.05,0,0,0')


# -- intrinsics --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Intrinsics:
    """``K`` (3x3, OpenCV convention), distortion ``D`` (plumb_bob or rational_polynomial; () for none)
    and the image size they were calibrated for (0 when unknown)."""

    K: np.ndarray
    D: tuple[float, ...] = ()
    width: int = 0
    height: int = 0
    frame_id: str = ''

    @classmethod
    def from_values(
        cls, fx: float, fy: float, cx: float, cy: float, distortion: Iterable[float] = ()
    ) -> Intrinsics:
        for name, value in (('fx', fx), ('fy', fy)):
            if not (math.isfinite(value) and value > 0):
                raise CalibrationError(f'--{name} {value}: a focal length in pixels must be positive')
        for name, value in (('cx', cx), ('cy', cy)):
            if not math.isfinite(value):
                raise CalibrationError(f'--{name} {value}: the principal point must be a finite number')
        return cls(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), tuple(distortion))

    @classmethod
    def from_matrix(
        cls,
        source: str,
        K: ArrayLike,
        D: Iterable[float] = (),
        model: str = 'plumb_bob',
        width: int = 0,
        height: int = 0,
        frame_id: str = '',
    ) -> Intrinsics:
        """Checked intrinsics from a CameraInfo or its YAML file (``source`` names it in errors)."""
        K = np.asarray(K, float).reshape(3, 3)
        if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise CalibrationError(
                f'{source}: the camera matrix has no focal length (K = {K.ravel().tolist()}): '
                'calibrate the camera first (camera_calibration) or give --fx --fy --cx --cy'
            )
        D = tuple(float(d) for d in D)
        if any(D) and model not in DISTORTION_MODELS:
            raise CalibrationError(
                f'{source}: distortion model {model!r} is not supported: '
                f'use {" or ".join(DISTORTION_MODELS)}, or --distortion with --fx --fy --cx --cy'
            )
        if D and len(D) not in (4, 5, 8):
            raise CalibrationError(f'{source}: expected 4, 5 or 8 distortion coefficients, got {len(D)}')
        return cls(K, D, int(width), int(height), frame_id)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def distortion(self) -> np.ndarray | None:
        """``D`` for OpenCV, None when the lens is ideal."""
        return np.asarray(self.D, float) if any(self.D) else None


def read_camera_info_yaml(path: str | Path) -> Intrinsics:
    """Intrinsics from a camera_calibration_parsers YAML file (what ROS camera drivers save).

    Keys used: ``image_width``, ``image_height``, ``camera_matrix.data`` (9 numbers),
    ``distortion_model`` and ``distortion_coefficients.data``.
    """
    try:
        data = yaml.safe_load(Path(path).read_text())
    except OSError as error:
        raise CalibrationError(f'--camera-info {path}: cannot read it: {error.strerror}') from None
    except yaml.YAMLError as error:
        raise CalibrationError(f'--camera-info {path}: not YAML: {str(error).splitlines()[0]}') from None

    def entry(key: str, count: int | None = None) -> list[float]:
        value = data.get(key) if isinstance(data, dict) else None
        numbers = value.get('data') if isinstance(value, dict) else None
        if (
            not isinstance(numbers, list)
            or (count is not None and len(numbers) != count)
            or not all(isinstance(n, int | float) and not isinstance(n, bool) for n in numbers)
        ):
            expected = f'{count} numbers' if count else 'a list of numbers'
            raise CalibrationError(
                f'--camera-info {path}: {key}.data: expected {expected} '
                '(a camera_calibration_parsers YAML file, as camera drivers save it)'
            )
        return [float(n) for n in numbers]

    K = entry('camera_matrix', 9)
    D = entry('distortion_coefficients') if 'distortion_coefficients' in data else []
    size = [data.get('image_width', 0), data.get('image_height', 0)]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v >= 0 for v in size):
        raise CalibrationError(f'--camera-info {path}: image_width, image_height: expected whole numbers')
    model = str(data.get('distortion_model', 'plumb_bob'))
    return Intrinsics.from_matrix(f'--camera-info {path}', K, D, model, *size)


# -- tags --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TagSighting:
    """One detected tag: its corners (4 x 2, aruco order: the printed tag's top-left first, clockwise)
    and its centre, both in OpenCV pixel coordinates of the (distorted) image."""

    id: int
    corners: np.ndarray
    centre: np.ndarray


def _undistort(points: ArrayLike, intrinsics: Intrinsics) -> np.ndarray:
    """Pixels of the distorted image -> pixels of the ideal pinhole camera with the same ``K``."""
    points = np.asarray(points, float).reshape(-1, 1, 2)
    if intrinsics.distortion is None:
        return points.reshape(-1, 2)
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    ideal = cv2.undistortPointsIter(points, intrinsics.K, intrinsics.distortion, None, intrinsics.K, criteria)
    return ideal.reshape(-1, 2)


def _distort(points: ArrayLike, intrinsics: Intrinsics) -> np.ndarray:
    """The inverse of :func:`_undistort`."""
    points = np.asarray(points, float).reshape(-1, 2)
    if intrinsics.distortion is None:
        return points
    rays = np.linalg.solve(intrinsics.K, np.c_[points, np.ones(len(points))].T).T
    pixels, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), intrinsics.K, intrinsics.distortion)
    return pixels.reshape(-1, 2)


def _line_through(a: Sequence[float], b: Sequence[float]) -> np.ndarray:
    return np.cross([a[0], a[1], 1.0], [b[0], b[1], 1.0])


def _meet(line_a: np.ndarray, line_b: np.ndarray) -> np.ndarray:
    point = np.cross(line_a, line_b)
    return point[:2] / point[2]


def tag_centre(corners: ArrayLike, intrinsics: Intrinsics) -> np.ndarray:
    """The pixel of a tag's centre: where the diagonals of its 4 corners cross (in the ideal image).

    >>> K = Intrinsics.from_values(500, 500, 400, 300)
    >>> tag_centre([[0, 0], [10, 0], [12, 8], [0, 10]], K).round(4).tolist()
    [6.0, 4.0]
    """
    a, b, c, d = _undistort(corners, intrinsics)
    centre = _meet(_line_through(a, c), _line_through(b, d))
    return _distort(centre, intrinsics)[0]


EDGE_SAMPLES = 24
"""Profiles across each edge of a tag's black square, for the line fit."""


def refine_tag_corners(gray: np.ndarray, corners: ArrayLike, intrinsics: Intrinsics) -> np.ndarray:
    """The corners of a tag's black square, as the crossings of lines fitted to its 4 outer edges.

    Each edge is sampled across at :data:`EDGE_SAMPLES` places over its middle three
    quarters; on each profile the edge is where the intensity crosses halfway from the
    black border to the white quiet zone (searched within 0.7 of a tag cell, the
    border's width). The points are undistorted, a line fitted through them; the
    corners are where neighbouring lines meet, distorted again. An edge with fewer
    than 5 usable profiles keeps the detector's corners.
    """
    corners = np.asarray(corners, float).reshape(4, 2)
    image = gray.astype(np.float32)
    middle = corners.mean(axis=0)
    lines = []
    for k in range(4):
        start, end = corners[k], corners[(k + 1) % 4]
        along = end - start
        length = float(np.linalg.norm(along))
        if length < 4.0:
            return corners
        along /= length
        outward = np.array([-along[1], along[0]])
        if np.dot(outward, (start + end) / 2.0 - middle) < 0:
            outward = -outward
        reach = max(1.5, 0.7 * length / 8.0)  # tag36h11 as aruco draws it: 8 cells across
        offsets = np.arange(-reach, reach + 1e-9, 0.125)
        stations = np.linspace(0.125, 0.875, EDGE_SAMPLES) * length
        where = start + stations[:, None, None] * along + offsets[None, :, None] * outward
        profiles = cv2.remap(
            image,
            where[..., 0].astype(np.float32),
            where[..., 1].astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
        found = []
        for station, profile in zip(stations, profiles, strict=True):
            low, high = float(profile.min()), float(profile.max())
            if high - low < 20.0:
                continue
            half = (low + high) / 2.0
            bright = profile >= half
            rises = np.flatnonzero(~bright[:-1] & bright[1:])
            if rises.size == 0:
                continue
            j = rises[0]
            t = (half - profile[j]) / (profile[j + 1] - profile[j])
            offset = offsets[j] + t * (offsets[j + 1] - offsets[j])
            found.append(start + station * along + offset * outward)
        if len(found) < 5:
            return corners
        points = _undistort(found, intrinsics).astype(np.float32)
        vx, vy, x0, y0 = cv2.fitLine(points, cv2.DIST_L2, 0, 0.01, 0.01).ravel()
        lines.append(_line_through((x0, y0), (x0 + vx, y0 + vy)))
    refined = np.array([_meet(lines[k - 1], lines[k]) for k in range(4)])
    if not np.all(np.isfinite(refined)) or np.max(np.abs(_distort(refined, intrinsics) - corners)) > 3.0:
        return corners
    return _distort(refined, intrinsics)


def detect_tags(image: np.ndarray, intrinsics: Intrinsics) -> dict[int, list[TagSighting]]:
    """Every tag36h11 tag in a BGR or grey image, by id (a list: an id may show more than once)."""
    gray = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    parameters = cv2.aruco.DetectorParameters_create()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    corners, ids, _ = cv2.aruco.detectMarkers(gray, dictionary, parameters=parameters)
    found: dict[int, list[TagSighting]] = {}
    for quad, tag_id in zip(corners, [] if ids is None else ids.ravel(), strict=True):
        refined = refine_tag_corners(gray, quad, intrinsics)
        sighting = TagSighting(int(tag_id), refined, tag_centre(refined, intrinsics))
        found.setdefault(int(tag_id), []).append(sighting)
    return found


def tag_points(tags: list[TagSpec], seen: dict[int, list[TagSighting]]) -> list[FloorPoint]:
    """The floor points of the tags asked for.

    :raises CalibrationError: a tag given twice, not seen, or seen more than once.
    """
    points = []
    given = set()
    for tag in tags:
        if tag.id in given:
            raise CalibrationError(f'tag {tag.id} is given twice: give each --tag id once')
        given.add(tag.id)
        sightings = seen.get(tag.id, [])
        if not sightings:
            ids = ', '.join(map(str, sorted(seen))) if seen else f'none: no {TAG_FAMILY} tag in the image'
            raise CalibrationError(
                f'tag {tag.id} is not seen in the image (tags seen: {ids}); '
                'check the --tag ids, and that each tag is whole, flat and in focus, with a white border '
                '(quiet zone) around its black square at least two of its cells wide (200 px around an '
                '800 px tag)'
            )
        if len(sightings) > 1:
            raise CalibrationError(
                f'tag {tag.id} is seen {len(sightings)} times in the image: '
                'each tag id must be on the floor once'
            )
        u, v = sightings[0].centre
        points.append(FloorPoint(f'tag {tag.id}', (float(u), float(v)), tag.floor))
    return points


# -- checks and solving ------------------------------------------------------------------------
def check_points(points: list[FloorPoint], width: int, height: int) -> None:
    """Refuse what gives no unique pose: too few points, points on one line or on the same spot,
    pixels outside the image.

    :raises CalibrationError: naming the points.
    """
    if len(points) < MIN_POINTS:
        raise CalibrationError(
            f'need at least {MIN_POINTS} floor points, got {len(points)}: '
            'add --tag ID:X,Y or --point U,V:X,Y entries'
        )
    for point in points:
        u, v = point.pixel
        if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
            raise CalibrationError(
                f'{point.label}: pixel ({u:g}, {v:g}) is outside the {width}x{height} image '
                '(OpenCV pixel coordinates: the top-left pixel is centred at 0,0)'
            )
    floor = np.array([p.floor for p in points], float)
    for i in range(len(points)):
        for j in range(i + 1, len(points)):
            if np.linalg.norm(floor[i] - floor[j]) < 1e-6:
                x, y = floor[i]
                raise CalibrationError(
                    f'{points[i].label} and {points[j].label} are both at map ({x:g}, {y:g}): '
                    'each point needs its own map position'
                )
    spread = np.linalg.svd(floor - floor.mean(axis=0), compute_uv=False)
    if spread[-1] < COLLINEAR_RATIO * spread[0]:
        raise CalibrationError(
            f'the {len(points)} floor points lie on one line, which leaves the camera free to turn '
            'about it: add points off that line'
        )


@dataclass(frozen=True)
class Calibration:
    """The solved pose: the optical frame in ``map`` (``rotation``'s columns are its x, y, z axes)."""

    points: tuple[FloorPoint, ...]
    reprojected: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    intrinsics: Intrinsics
    width: int
    height: int
    notes: tuple[str, ...] = field(default=())

    # -- quality -------------------------------------------------------------------------------
    @property
    def errors(self) -> np.ndarray:
        """Per point, pixels between where it is seen and where the pose projects it."""
        return np.linalg.norm(self.reprojected - np.array([p.pixel for p in self.points]), axis=1)

    @property
    def rms_error(self) -> float:
        return float(np.sqrt(np.mean(self.errors**2)))

    @property
    def max_error(self) -> float:
        return float(np.max(self.errors))

    # -- pose ----------------------------------------------------------------------------------
    @property
    def quaternion(self) -> tuple[float, float, float, float]:
        """(x, y, z, w) of ``rotation``, w >= 0."""
        return quaternion_from_matrix(self.rotation)

    @property
    def target(self) -> np.ndarray:
        """Where the optical axis meets the floor (1 m ahead if it never does)."""
        forward = self.rotation[:, 2]
        if forward[2] < -1e-9:
            return self.translation - forward * (self.translation[2] / forward[2])
        return self.translation + forward

    @property
    def up(self) -> np.ndarray:
        """The image's up direction in ``map``: minus the optical y axis."""
        return -self.rotation[:, 1]

    @property
    def fov_deg(self) -> float:
        """Vertical field of view, as a world file's ``fov_deg``: 2 atan((H / 2) / fy)."""
        return math.degrees(2.0 * math.atan2(self.height / 2.0, self.intrinsics.fy))

    # -- output --------------------------------------------------------------------------------
    def static_transform_args(self, frame: str, parent: str = 'map') -> str:
        """``x y z qx qy qz qw parent frame``: tf2's static_transform_publisher arguments."""
        values = [*self.translation, *self.quaternion]
        return ' '.join(f'{v:.6f}' for v in values) + f' {parent} {frame}'

    def command(self, frame: str, parent: str = 'map') -> str:
        return f'{STATIC_TRANSFORM_PUBLISHER} {self.static_transform_args(frame, parent)}'

    def world_entry(self, name: str) -> dict:
        """The ``vision_systems`` entry of a world file (:func:`drvs.sim.world_file.load_world`)."""
        entry = {
            'name': name,
            'position': [_round(v, 4) for v in self.translation],
            'target': [_round(v, 4) for v in self.target],
            'up': [_round(v, 6) for v in self.up],
            'fov_deg': _round(self.fov_deg, 4),
            'resolution': [self.width, self.height],
        }
        distortion = list(self.intrinsics.D[:5]) + [0.0] * (5 - len(self.intrinsics.D[:5]))
        if any(distortion):
            entry['distortion'] = [_round(v, 10) for v in distortion]
        return entry

    def world_entry_yaml(self, name: str) -> str:
        """:meth:`world_entry` as one YAML flow mapping."""
        entry = self.world_entry(name)
        parts = []
        for key, value in entry.items():
            if key == 'name':
                text = value if yaml.safe_load(value) == value else f'"{value}"'
            elif isinstance(value, list):
                text = '[' + ', '.join(_number(v) for v in value) + ']'
            else:
                text = _number(value)
            parts.append(f'{key}: {text}')
        return '{' + ', '.join(parts) + '}'

    def report(self, name: str, frame: str) -> str:
        """The text ``drvs_calibrate`` prints."""
        lines = [f'{len(self.points)} floor points (pixels: OpenCV coordinates; map: metres):']
        width = max(len(p.label) for p in self.points)
        for point, seen, error in zip(self.points, self.reprojected, self.errors, strict=True):
            lines.append(
                f'  {point.label:<{width}}  pixel {point.pixel[0]:9.3f} {point.pixel[1]:9.3f}'
                f'  map {point.floor[0]:8.3f} {point.floor[1]:8.3f}'
                f'  reprojected {seen[0]:9.3f} {seen[1]:9.3f}  error {error:.3f} px'
            )
        worst = self.points[int(np.argmax(self.errors))].label
        x, y, z = self.translation
        tx, ty, _ = self.target
        lines += [
            f'reprojection error: rms {self.rms_error:.3f} px, max {self.max_error:.3f} px ({worst})',
            f'camera in map: position {x:.4f} {y:.4f} {z:.4f}, looking at {tx:.4f} {ty:.4f} on the floor',
            f'static transform (x y z qx qy qz qw parent child): {self.static_transform_args(frame)}',
            self.command(frame),
            'world file entry (under vision_systems:):',
            f'  - {self.world_entry_yaml(name)}',
        ]
        return '\n'.join(lines)

    def to_json(self, name: str, frame: str) -> dict:
        """Everything :meth:`report` says, machine-readably."""
        return {
            'points': [
                {
                    'label': p.label,
                    'pixel': list(p.pixel),
                    'map': [*p.floor, 0.0],
                    'reprojected': seen.tolist(),
                    'error_px': float(error),
                }
                for p, seen, error in zip(self.points, self.reprojected, self.errors, strict=True)
            ],
            'rms_error_px': self.rms_error,
            'max_error_px': self.max_error,
            'parent': 'map',
            'frame': frame,
            'position': self.translation.tolist(),
            'quaternion_xyzw': list(self.quaternion),
            'rotation': self.rotation.tolist(),
            'target': self.target.tolist(),
            'up': self.up.tolist(),
            'fov_deg': self.fov_deg,
            'resolution': [self.width, self.height],
            'static_transform_publisher': self.static_transform_args(frame),
            'command': self.command(frame),
            'world_entry': self.world_entry(name),
            'world_entry_yaml': self.world_entry_yaml(name),
            'intrinsics': {'K': self.intrinsics.K.tolist(), 'D': list(self.intrinsics.D)},
            'notes': list(self.notes),
        }


def _round(value: float, digits: int) -> float:
    value = round(float(value), digits)
    return 0.0 if value == 0 else value


def _number(value: float) -> str:
    """A YAML number that reads back as the same int or float (PyYAML wants a '.' in floats)."""
    if isinstance(value, int):
        return str(value)
    text = f'{value:.10f}'.rstrip('0')
    return text + '0' if text.endswith('.') else text


def quaternion_from_matrix(rotation: ArrayLike) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, w >= 0.

    >>> [round(q, 6) for q in quaternion_from_matrix([[0, -1, 0], [1, 0, 0], [0, 0, 1]])]
    [0.0, 0.0, 0.707107, 0.707107]
    """
    m = np.asarray(rotation, float)
    # The largest of 4|w|^2, 4|x|^2, ... is computed first for a well-conditioned division.
    trace = np.trace(m)
    candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
    i = int(np.argmax(candidates))
    if i == 0:
        s = math.sqrt(1.0 + trace) * 2.0
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4.0]
    elif i == 1:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2.0
        q = [s / 4.0, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif i == 2:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2.0
        q = [(m[0, 1] + m[1, 0]) / s, s / 4.0, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2.0
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4.0, (m[1, 0] - m[0, 1]) / s]
    unit = np.array(q) / np.linalg.norm(q)
    if unit[3] < 0:
        unit = -unit
    x, y, z, w = (float(v) + 0.0 for v in unit)
    return x, y, z, w


def _object_points(points: Sequence[FloorPoint]) -> np.ndarray:
    return np.array([[*p.floor, 0.0] for p in points], float).reshape(-1, 1, 3)


def _pose(
    points: Sequence[FloorPoint],
    intrinsics: Intrinsics,
    rvec: np.ndarray,
    tvec: np.ndarray,
    width: int,
    height: int,
    notes: Iterable[str] = (),
) -> Calibration:
    camera_from_map = cv2.Rodrigues(rvec)[0]
    reprojected, _ = cv2.projectPoints(
        _object_points(points), rvec, tvec, intrinsics.K, intrinsics.distortion
    )
    return Calibration(
        points=tuple(points),
        reprojected=reprojected.reshape(-1, 2),
        rotation=camera_from_map.T,
        translation=-camera_from_map.T @ np.asarray(tvec, float).ravel(),
        intrinsics=intrinsics,
        width=width,
        height=height,
        notes=tuple(notes),
    )


def check_pose(calibration: Calibration) -> None:
    """Refuse a pose that cannot be: a point behind the camera, or the camera under the floor.

    :raises CalibrationError: naming the point or the height, and the likely mistake.
    """
    floor = np.array([[*p.floor, 0.0] for p in calibration.points])
    depths = (floor - calibration.translation) @ calibration.rotation[:, 2]
    for point, depth in zip(calibration.points, depths, strict=True):
        if depth <= 0:
            raise CalibrationError(
                f'the best pose puts {point.label} behind the camera (depth {depth:.3f} m): '
                'check that each pixel matches its map point'
            )
    if calibration.translation[2] <= 0:
        raise CalibrationError(
            f'the best pose puts the camera under the floor (z = {calibration.translation[2]:.3f} m): '
            'are the map x and y swapped or mirrored?'
        )


def solve(points: list[FloorPoint], intrinsics: Intrinsics, width: int, height: int) -> Calibration:
    """The pose of the camera's optical frame in ``map`` from checked floor points.

    Candidates from IPPE (made for planar points; it returns both poses of its
    two-fold ambiguity), SQPnP and the iterative method, each refined with
    Levenberg-Marquardt; the one with the smallest reprojection error wins.

    :raises CalibrationError: no candidate, or the best one puts a point behind the
        camera or the camera under the floor (:func:`check_pose`).
    """
    check_points(points, width, height)
    objects = _object_points(points)
    pixels = np.array([p.pixel for p in points], float).reshape(-1, 1, 2)
    K, D = intrinsics.K, intrinsics.distortion
    best, best_error = None, math.inf
    for method in (cv2.SOLVEPNP_IPPE, cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_ITERATIVE):
        try:
            count, rvecs, tvecs, _ = cv2.solvePnPGeneric(objects, pixels, K, D, flags=method)
        except cv2.error:
            continue
        for rvec, tvec in zip(rvecs[:count], tvecs[:count], strict=True):
            rvec, tvec = cv2.solvePnPRefineLM(objects, pixels, K, D, rvec, tvec)
            if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
                continue
            projected, _ = cv2.projectPoints(objects, rvec, tvec, K, D)
            error = float(np.sum((projected - pixels) ** 2))
            if error < best_error:
                best, best_error = (rvec, tvec), error
    if best is None:
        raise CalibrationError(
            f'cv2.solvePnP found no pose for these {len(points)} points: '
            'check that each pixel matches its map point and the intrinsics'
        )
    calibration = _pose(points, intrinsics, *best, width, height, _notes(intrinsics, width, height))
    check_pose(calibration)
    return calibration


def _notes(intrinsics: Intrinsics, width: int, height: int) -> list[str]:
    """What a world file's ideal camera leaves out of this one."""
    notes = []
    fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
    off_centre = max(abs(cx - (width - 1) / 2.0), abs(cy - (height - 1) / 2.0))
    if abs(fx - fy) > 0.01 * fy or off_centre > max(2.0, 0.01 * max(width, height)):
        notes.append(
            'a world file camera has square pixels and its principal point at the image centre; '
            f'this one has fx {fx:.2f}, fy {fy:.2f}, cx {cx:.2f}, cy {cy:.2f}: fov_deg is from fy'
        )
    if any(intrinsics.D[5:]):
        notes.append('a world file camera takes plumb_bob distortion (5 numbers); k4 to k6 are left out')
    return notes
