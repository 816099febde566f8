"""An exact 3-D ray trace of a double-pass plane-mirror interferometer, written independently of
the twin's optics (no unfolding, no cosine formula): rays are intersected with finite planes and
reflected one surface at a time, and the optical path is summed segment by segment.

The head: a polarising beam splitter (its diagonal a plane: the measurement beam passes it on the
way in and out, and reflects on it on the way to and from the cube corner, as the quarter-wave
plate's two passes turn the polarisation) and a hollow cube corner beside it with three real,
mutually perpendicular, square mirror faces. The path: source plane -> beam splitter (pass) ->
[fold mirror] -> target mirror -> [fold mirror] -> beam splitter (reflect) -> cube corner (three
faces, in whatever order the ray meets them) -> beam splitter (reflect) -> [fold mirror] ->
target mirror -> [fold mirror] -> beam splitter (pass) -> back to the source plane. The reading
is the optical path / 4 (the double pass's four trips). Hollow, air-spaced optics, index 1:
the index is the twin's separate factor. Units: m."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class TraceError(AssertionError):
    """A ray that misses a surface it must hit (the trace's geometry is wrong)."""


@dataclass(frozen=True)
class Mirror:
    """A plane mirror: a point on it, its unit normal, and its half-size around the point
    (the ray must land within ``half_size_m`` of ``point``)."""
    point: np.ndarray
    normal: np.ndarray
    half_size_m: float

    def hit(self, origin, direction):
        """(distance along the ray, hit point); TraceError if the ray misses."""
        denom = direction @ self.normal
        if abs(denom) < 1e-12:
            raise TraceError("ray parallel to the mirror")
        t = ((self.point - origin) @ self.normal) / denom
        x = origin + t * direction
        if t <= 0 or np.linalg.norm(x - self.point) > self.half_size_m:
            raise TraceError(f"ray misses the mirror at {self.point} (t = {t}, "
                             f"off by {np.linalg.norm(x - self.point)} m)")
        return t, x

    def reflect(self, direction):
        return direction - 2.0 * (direction @ self.normal) * self.normal


@dataclass(frozen=True)
class CubeCorner:
    """A hollow cube corner: vertex and the three unit normals of its faces (mutually
    perpendicular, pointing into the corner's open side); each face is the square
    0 <= (x - vertex) . e_j <= size for the two other normals e_j."""
    vertex: np.ndarray
    normals: tuple
    size_m: float

    def trace(self, origin, direction):
        """(optical path inside, exit point, exit direction) of a ray entering the corner."""
        length, x, d = 0.0, origin, direction
        for _ in range(3):
            best = None
            for i, e in enumerate(self.normals):
                if d @ e >= 0:
                    continue                       # moving away from this face's plane
                t = -((x - self.vertex) @ e) / (d @ e)
                p = x + t * d
                others = [(p - self.vertex) @ self.normals[j] for j in range(3) if j != i]
                if t > 1e-15 and all(-1e-12 <= c <= self.size_m for c in others):
                    if best is None or t < best[0]:
                        best = (t, p, e)
            if best is None:
                raise TraceError("ray leaves the cube corner before its third face")
            t, x, e = best
            length += t
            d = d - 2.0 * (d @ e) * e
        return length, x, d


@dataclass(frozen=True)
class Head:
    """An interferometer head: source point and direction of the input beam, the beam splitter's
    diagonal (a Mirror) and the cube corner."""
    source: np.ndarray
    direction: np.ndarray
    splitter: Mirror
    corner: CubeCorner

    def effective_vertex(self) -> np.ndarray:
        """The cube corner's vertex seen through the beam splitter's diagonal (its image)."""
        n, p = self.splitter.normal, self.splitter.point
        return self.corner.vertex - 2.0 * ((self.corner.vertex - p) @ n) * n


def make_head(vertex_image, beam_direction, entry_offset_m, across, corner_size_m=0.015,
              corner_twist_rad=0.1) -> Head:
    """A head whose cube corner, seen through the beam splitter, has its vertex at
    ``vertex_image``, whose input beam runs along ``beam_direction`` at ``entry_offset_m`` along
    ``across`` (made normal to the beam) from the line through that vertex, the source 0.05 m
    behind that vertex. The splitter's diagonal (45 deg) sits 0.04 m in front of the vertex
    image and turns the returning beam towards the real cube corner, 0.04 m to the side along
    ``across``; the corner's faces are twisted about its body diagonal by ``corner_twist_rad``
    so that no face is aligned with the beams."""
    b = beam_direction / np.linalg.norm(beam_direction)
    u = across - (across @ b) * b
    u = u / np.linalg.norm(u)
    centre = vertex_image + 0.04 * b
    n_split = (b + u) / np.sqrt(2.0)                 # the returning beam (-b) reflects to +u
    splitter = Mirror(centre, n_split, 0.03)
    vertex = vertex_image - 2.0 * ((vertex_image - centre) @ n_split) * n_split
    # the corner's body diagonal points back along -u (its open side faces the splitter); its
    # face normals: a right-handed orthonormal set, each at acos(1/sqrt 3) from the diagonal
    axis = -u
    w = np.cross(axis, b)
    w /= np.linalg.norm(w)
    v = np.cross(w, axis)
    normals = tuple(axis / np.sqrt(3.0) + np.sqrt(2.0 / 3.0)
                    * (np.cos(phi) * v + np.sin(phi) * w)
                    for phi in corner_twist_rad + 2.0 * np.pi * np.arange(3) / 3.0)
    gram = np.array([[a @ c for c in normals] for a in normals])
    if not np.allclose(gram, np.eye(3), atol=1e-15):
        raise TraceError("cube-corner faces not mutually perpendicular")
    source = vertex_image + entry_offset_m * u - 0.05 * b
    return Head(source=source, direction=b, splitter=splitter,
                corner=CubeCorner(vertex, normals, corner_size_m))


def trace_reading(head: Head, target: Mirror, folds=()) -> tuple[float, np.ndarray]:
    """(reading = optical path / 4 (m), exit direction) of the double-pass beam of ``head`` on the
    ``target`` mirror, through the fixed ``folds`` mirrors in order (the Z fold mirror)."""
    b = head.direction
    x, d, path = head.source, b, 0.0

    def go(mirror, reflect=True):
        nonlocal x, d, path
        t, x = mirror.hit(x, d)
        path += t
        if reflect:
            d = mirror.reflect(d)

    def to_target_and_back():
        for f in folds:
            go(f)
        go(target)
        for f in reversed(folds):
            go(f)

    go(head.splitter, reflect=False)          # measurement polarisation passes
    to_target_and_back()
    go(head.splitter)                         # quarter-wave plate passed twice: reflects
    t, x, d = head.corner.trace(x, d)
    path += t
    go(head.splitter)
    to_target_and_back()
    go(head.splitter, reflect=False)          # passes again, out of the head
    # back to the source plane (normal b through the source)
    denom = d @ b
    t = ((head.source - x) @ b) / denom
    if t <= 0:
        raise TraceError("output beam does not return to the source plane")
    path += t
    return path / 4.0, d
