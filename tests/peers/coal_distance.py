"""A collision checker we did not write, on the URDF `rigbridge config urdf` writes: PyPI's
`coal` (the successor of FCL, from the HPP/Pinocchio team) measures the distances; this
script only reads the URDF and SRDF itself (xml.etree), does forward kinematics from the
URDF's joints (origins, rpy, axes), and picks the closest checked pair of links.

Usage: coal_distance.py ROBOT.urdf ROBOT.srdf JOINTS.csv MARGIN_M
JOINTS.csv: header j1..jN, one row per configuration, degrees for revolute joints (metres
for prismatic ones), jK the K-th moving joint from the root. Prints one CSV line per row:
min_clearance_m,link_a,link_b,status (status free / within_margin / collision: <= 0 is a
collision, below MARGIN_M within the margin), then on stderr the time taken.

Which pairs are checked: every two links that carry collision geometry, except links joined
to each other by fixed joints only (they cannot move against each other) and the pairs the
SRDF lists in `disable_collisions`. A link's distance to another is the smallest over their
`<collision>` elements (a capsule written as a cylinder and two spheres is their union).
The closest pair is exact: pairs are measured in order of a lower bound (centre distance
less bounding radii), stopping once no unmeasured pair can be closer.
"""
import csv
import math
import sys
import time
import xml.etree.ElementTree as ET

import coal
import numpy as np


def vec(text, default="0 0 0"):
    return np.array([float(v) for v in (text or default).split()])


def rpy_matrix(rpy):
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    # URDF: fixed axes x, then y, then z: R = Rz(yaw) Ry(pitch) Rx(roll).
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def origin_of(element):
    t = np.eye(4)
    origin = element.find("origin") if element is not None else None
    if origin is not None:
        t[:3, :3] = rpy_matrix(vec(origin.get("rpy")))
        t[:3, 3] = vec(origin.get("xyz"))
    return t


def axis_rotation(axis, angle):
    x, y, z = axis / np.linalg.norm(axis)
    c, s = math.cos(angle), math.sin(angle)
    C = 1.0 - c
    return np.array([
        [c + x * x * C, x * y * C - z * s, x * z * C + y * s],
        [y * x * C + z * s, c + y * y * C, y * z * C - x * s],
        [z * x * C - y * s, z * y * C + x * s, c + z * z * C],
    ])


def read_obj_points(path):
    points = []
    with open(path) as f:
        for line in f:
            parts = line.split()
            if parts and parts[0] == "v":
                points.append([float(v) for v in parts[1:4]])
    return np.array(points)


def geometry(element, directory):
    """A coal shape and its bounding radius about its origin."""
    box = element.find("box")
    if box is not None:
        size = vec(box.get("size"))
        return coal.Box(*size), float(np.linalg.norm(size) / 2)
    cylinder = element.find("cylinder")
    if cylinder is not None:
        r, length = float(cylinder.get("radius")), float(cylinder.get("length"))
        return coal.Cylinder(r, length), math.hypot(r, length / 2)
    sphere = element.find("sphere")
    if sphere is not None:
        r = float(sphere.get("radius"))
        return coal.Sphere(r), r
    mesh = element.find("mesh")
    if mesh is not None:
        points = read_obj_points(f"{directory}/{mesh.get('filename')}")
        vertices = coal.StdVec_Vec3s()
        for p in points:
            vertices.append(p)
        hull = coal.Convex.convexHull(vertices, False, "")
        return hull, float(np.max(np.linalg.norm(points, axis=1)))
    raise SystemExit(f"unsupported geometry in {ET.tostring(element)[:80]}")


class Robot:
    def __init__(self, urdf_path, srdf_path):
        directory = urdf_path.rsplit("/", 1)[0] if "/" in urdf_path else "."
        root = ET.parse(urdf_path).getroot()
        self.elements = []  # (link, coal shape, placement in link, bounding radius)
        for link in root.findall("link"):
            for collision in link.findall("collision"):
                shape, radius = geometry(collision.find("geometry"), directory)
                self.elements.append((link.get("name"), shape, origin_of(collision), radius))
        self.joints = {}  # child -> (parent, origin, kind, axis)
        for joint in root.findall("joint"):
            child = joint.find("child").get("link")
            axis = joint.find("axis")
            self.joints[child] = (
                joint.find("parent").get("link"),
                origin_of(joint),
                joint.get("type"),
                vec(axis.get("xyz") if axis is not None else None, "1 0 0"),
            )
        links = [l.get("name") for l in root.findall("link")]
        roots = [l for l in links if l not in self.joints]
        assert len(roots) == 1, f"one root link, found {roots}"
        # Depth-first from the root: the order moving joints take their j1..jN columns.
        children = {}
        for child, (parent, *_rest) in self.joints.items():
            children.setdefault(parent, []).append(child)
        self.order, self.moving = [], {}
        stack = [roots[0]]
        while stack:
            link = stack.pop()
            self.order.append(link)
            if link in self.joints and self.joints[link][2] in ("revolute", "continuous", "prismatic"):
                self.moving[link] = len(self.moving)
            stack.extend(reversed(children.get(link, [])))
        self.root = roots[0]
        self.rigid = {link: self.rigid_group(link) for link in links}
        disabled = set()
        for pair in ET.parse(srdf_path).getroot().findall("disable_collisions"):
            disabled.add(frozenset((pair.get("link1"), pair.get("link2"))))
        names = sorted({e[0] for e in self.elements})
        link_pairs = set()
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                if self.rigid[a] != self.rigid[b] and frozenset((a, b)) not in disabled:
                    link_pairs.add((a, b))
        self.pairs = np.array([
            (i, j)
            for i, ei in enumerate(self.elements)
            for j, ej in enumerate(self.elements)
            if (ei[0], ej[0]) in link_pairs
        ])
        self.radii = np.array([e[3] for e in self.elements])
        self.request = coal.DistanceRequest()
        # GJK to 1e-9 m (coal's default is 1e-6): the comparison is to 1e-4 m, and a
        # status flips only when a distance is within the tolerance of 0 or the margin.
        self.request.gjk_tolerance = 1e-9
        self.result = coal.DistanceResult()

    def rigid_group(self, link):
        """The link nearest the root that `link` hangs from through fixed joints only."""
        while link in self.joints and self.joints[link][2] == "fixed":
            link = self.joints[link][0]
        return link

    def poses(self, q):
        world = {self.root: np.eye(4)}
        for link in self.order[1:]:
            parent, origin, kind, axis = self.joints[link]
            t = world[parent] @ origin
            if link in self.moving:
                motion = np.eye(4)
                value = q[self.moving[link]]
                if kind == "prismatic":
                    motion[:3, 3] = axis * value
                else:
                    motion[:3, :3] = axis_rotation(axis, value)
                t = t @ motion
            world[link] = t
        return world

    def closest(self, q):
        world = self.poses(q)
        placed = [world[link] @ placement for link, _, placement, _ in self.elements]
        centres = np.array([p[:3, 3] for p in placed])
        gaps = centres[self.pairs[:, 0]] - centres[self.pairs[:, 1]]
        bounds = np.linalg.norm(gaps, axis=1) - self.radii[self.pairs[:, 0]] - self.radii[self.pairs[:, 1]]
        best = (math.inf, "", "")
        for k in np.argsort(bounds):
            if bounds[k] >= best[0] or best[0] <= 0.0:
                break
            i, j = self.pairs[k]
            a, b = placed[i], placed[j]
            self.result.clear()
            d = coal.distance(
                self.elements[i][1], coal.Transform3s(a[:3, :3], a[:3, 3]),
                self.elements[j][1], coal.Transform3s(b[:3, :3], b[:3, 3]),
                self.request, self.result,
            )
            if d < best[0]:
                best = (d, self.elements[i][0], self.elements[j][0])
        return best

    def joint_kinds(self):
        kinds = [None] * len(self.moving)
        for link, index in self.moving.items():
            kinds[index] = self.joints[link][2]
        return kinds


def main():
    urdf, srdf, joints_csv, margin = sys.argv[1:5]
    margin = float(margin)
    robot = Robot(urdf, srdf)
    kinds = robot.joint_kinds()
    start = time.monotonic()
    out = sys.stdout
    rows = 0
    with open(joints_csv, newline="") as f:
        reader = csv.DictReader(f)
        for row in reader:
            q = [
                float(row[f"j{k + 1}"]) if kind == "prismatic" else math.radians(float(row[f"j{k + 1}"]))
                for k, kind in enumerate(kinds)
            ]
            d, a, b = robot.closest(q)
            status = "collision" if d <= 0.0 else "within_margin" if d < margin else "free"
            out.write(f"{d:.9f},{a},{b},{status}\n")
            rows += 1
    print(f"coal peer: {rows} rows in {time.monotonic() - start:.1f} s", file=sys.stderr)


if __name__ == "__main__":
    main()
