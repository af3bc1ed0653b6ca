"""Forbidden workspace zones in the base frame (boxes and spheres) and the velocity filter that keeps a point out
of them: the component of motion into a zone is limited so the point glides along the zone's boundary.

Used by the emulated DSP (protection zones around the base and the user, like the real arm's) and by the safety
service's workspace check.
"""
from __future__ import annotations

import math
from typing import Optional, Union

import numpy as np

from protocol import kinova
from services.runtime.config import ConfigStruct

Vec3 = tuple[float, float, float]


class BoxZone(ConfigStruct, tag="box", tag_field="shape"):
    """Axis-aligned box in the base frame."""

    name: str = "box"
    min_xyz: Vec3 = (0.0, 0.0, 0.0)
    max_xyz: Vec3 = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if any(not math.isfinite(v) for v in (*self.min_xyz, *self.max_xyz)):
            raise ValueError(f"zone {self.name}: bounds must be finite")
        if any(a >= b for a, b in zip(self.min_xyz, self.max_xyz, strict=True)):
            raise ValueError(f"zone {self.name}: min_xyz must be below max_xyz on every axis")

    def signed_distance(self, p: np.ndarray) -> tuple[float, np.ndarray]:
        """(d, n): distance from the zone (negative inside) and the outward unit normal at the nearest point."""
        lo, hi = np.asarray(self.min_xyz), np.asarray(self.max_xyz)
        centre, half = (lo + hi) / 2.0, (hi - lo) / 2.0
        local = p - centre
        q = np.abs(local) - half
        if np.all(q <= 0.0):  # inside: the nearest face
            axis = int(np.argmax(q))
            n = np.zeros(3)
            n[axis] = 1.0 if local[axis] >= 0 else -1.0
            return float(q[axis]), n
        outside = np.maximum(q, 0.0)
        d = float(np.linalg.norm(outside))
        n = np.sign(local) * outside / d
        return d, n


class SphereZone(ConfigStruct, tag="sphere", tag_field="shape"):
    name: str = "sphere"
    centre: Vec3 = (0.0, 0.0, 0.0)
    radius_m: float = 0.1

    def __post_init__(self) -> None:
        if not (self.radius_m > 0 and math.isfinite(self.radius_m)) or any(not math.isfinite(v) for v in self.centre):
            raise ValueError(f"zone {self.name}: radius must be positive and the centre finite")

    def signed_distance(self, p: np.ndarray) -> tuple[float, np.ndarray]:
        offset = p - np.asarray(self.centre)
        r = float(np.linalg.norm(offset))
        n = offset / r if r > 1e-12 else np.array([0.0, 0.0, 1.0])
        return r - self.radius_m, n


Zone = Union[BoxZone, SphereZone]


def default_base_zone() -> BoxZone:
    """The arm's own column and mounting: the end effector stays out of a box around the base (like the real
    arm's base protection zone)."""
    return BoxZone(name="base", min_xyz=(-0.17, -0.17, -0.05), max_xyz=(0.17, 0.17, 0.33))


class ZoneFilterConfig(ConfigStruct):
    #: the filtered point keeps this far outside every zone (m)
    margin_m: float = 0.01
    #: inward speed allowed at distance d beyond the margin: gain·d (1/s); the point approaches exponentially
    approach_gain: float = 8.0
    #: how fast a point found inside a zone is pushed out (m/s per m of penetration), and at most how fast
    max_exit_speed_mps: float = 0.05


def nearest_zone(zones, p) -> tuple[Optional[object], float]:
    """The zone closest to p (or containing it) and the signed distance to it."""
    best, best_d = None, math.inf
    for zone in zones:
        d, _ = zone.signed_distance(np.asarray(p, dtype=float))
        if d < best_d:
            best, best_d = zone, d
    return best, best_d


def filter_velocity(zones, p, v, cfg: ZoneFilterConfig, dt: float) -> tuple[np.ndarray, list[str]]:
    """Limit the linear velocity v of point p so it never enters a zone: at distance d (beyond the margin) the
    speed into a zone is at most min(approach_gain·d, d/dt); tangential motion is kept, so the point glides along
    the boundary. Returns the filtered velocity and the names of the zones that constrained it."""
    p = np.asarray(p, dtype=float)
    v = np.array(v, dtype=float, copy=True)
    active: list[str] = []
    for _ in range(3):  # a few passes settle corners where two zones meet
        changed = False
        for zone in zones:
            d, n = zone.signed_distance(p)
            d -= cfg.margin_m
            inward = -float(v @ n)
            if d <= 0.0:
                allowed = -min(cfg.max_exit_speed_mps, -d * cfg.approach_gain)  # must move out
            else:
                allowed = min(cfg.approach_gain * d, d / dt)
            if inward > allowed + 1e-12:
                v += (inward - allowed) * n
                changed = True
                if zone.name not in active:
                    active.append(zone.name)
        if not changed:
            break
    return v, active


def zone_from_kinova(zone: kinova.Zone) -> BoxZone:
    """A Kinova protection zone as a box: PrismSquareBase_Z with points 0-3 the base corners and point 4's Z the
    top (the SDK example's reading; other shapes are refused)."""
    if zone.zoneShape.shapeType != kinova.ShapeType.PrismSquareBase_Z:
        raise ValueError(f"zone {zone.ID}: only PrismSquareBase_Z zones are supported, got "
                         f"{kinova.ShapeType(zone.zoneShape.shapeType).name}")
    base = zone.zoneShape.Points[:4]
    xs, ys = [c.X for c in base], [c.Y for c in base]
    z0, z1 = min(c.Z for c in base), zone.zoneShape.Points[4].Z
    return BoxZone(name=f"kinova_{zone.ID}", min_xyz=(min(xs), min(ys), min(z0, z1)),
                   max_xyz=(max(xs), max(ys), max(z0, z1)))


def zone_to_kinova(box: BoxZone, zone_id: int) -> kinova.Zone:
    lo, hi = box.min_xyz, box.max_xyz
    corners = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])]
    points = [kinova.CartesianInfo(X=x, Y=y, Z=lo[2]) for x, y in corners]
    points += [kinova.CartesianInfo(X=x, Y=y, Z=hi[2]) for x, y in corners]
    return kinova.Zone(ID=zone_id, zoneShape=kinova.ZoneShape(shapeType=kinova.ShapeType.PrismSquareBase_Z,
                                                              Points=points))

