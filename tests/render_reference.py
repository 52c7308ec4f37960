"""A slow, obvious path tracer for a handful of pixels: the oracle of ``tests/test_render.py``.

Plain Python and NumPy, brute-force intersection (:func:`kdtrace.oracle.intersect_brute_force`),
one ray at a time. It draws its random numbers from the kernel's counter-based RNG with
the same keys (seed, pixel, sample, dimension), so the two renderers follow the same
paths and their pixels agree to rounding. Supports diffuse, mirror and dielectric
materials, one-sided emitters, a constant sky and flat normals only (no shading normals
or textures), with the conventions listed in :mod:`kdtrace._render_kernels`.
"""

from __future__ import annotations

import math

import numpy as np

from kdtrace._render_kernels import CAMERA_DIMS, DIMS_PER_BOUNCE, RAY_EPSILON, SHADOW_EPSILON, fresnel_dielectric, sample_key, uniform
from kdtrace.oracle import intersect_brute_force
from kdtrace.rays import pinhole_directions
from kdtrace.scene import Scene


class ReferenceTracer:
    """Path tracer over a scene's float32 triangles with Mitsuba's ``max_depth`` convention."""

    def __init__(self, scene: Scene, max_depth: int, seed: int, rr_depth: int = 5):
        if scene.normals is not None:
            raise ValueError("the reference tracer handles flat normals only")
        self.scene = scene
        self.max_depth = max_depth
        self.seed = seed
        self.rr_depth = rr_depth
        self.corners = scene.vertices.astype(np.float64)[scene.triangles]
        self.skip = scene.degenerate_mask()
        cross = np.cross(self.corners[:, 1] - self.corners[:, 0], self.corners[:, 2] - self.corners[:, 0])
        self.area = 0.5 * np.linalg.norm(cross, axis=1)
        self.normal = cross / np.maximum(2.0 * self.area, 1e-300)[:, None]
        emission = np.array([m.emission for m in scene.materials])[scene.material_ids]
        power = self.area * emission.mean(axis=1)
        self.emitters = np.flatnonzero(power > 0.0)
        self.select = power[self.emitters] / power[self.emitters].sum() if len(self.emitters) else np.zeros(0)
        self.sky = np.array(scene.sky.radiance if scene.sky is not None else (0.0, 0.0, 0.0))

    # -------------------------------------------------------------- helpers
    def _hit(self, origin, direction, tmax=np.inf):
        t, tri, u, v = intersect_brute_force(self.scene.vertices, self.scene.triangles, origin[None], direction[None],
                                             0.0, tmax, self.skip)
        return float(t[0]), int(tri[0]), float(u[0]), float(v[0])

    @staticmethod
    def _offset(p, n, d):
        magnitude = (1.0 + np.abs(p).max()) * RAY_EPSILON
        return p + (magnitude if n @ d >= 0.0 else -magnitude) * n

    def _light_pdf(self, tri):
        """Area pdf of NEE choosing a point on emitter triangle ``tri``."""
        k = np.flatnonzero(self.emitters == tri)
        return float(self.select[k[0]] / self.area[tri]) if len(k) else 0.0

    def _emission(self, tri):
        return np.array(self.scene.materials[self.scene.material_ids[tri]].emission)

    # -------------------------------------------------------------- one path
    def radiance(self, origin, direction, key):
        """Radiance of one path; random numbers ``uniform(key, dim)`` as in the kernel."""
        L = np.zeros(3)
        beta = np.ones(3)
        eta = 1.0
        prev_pdf, prev_delta = 0.0, True
        depth = 0
        o, d = np.asarray(origin, float), np.asarray(direction, float)
        while True:
            t, tri, u, v = self._hit(o, d)
            if tri < 0:
                return L + beta * self.sky
            material = self.scene.materials[self.scene.material_ids[tri]]
            p = (1 - u - v) * self.corners[tri, 0] + u * self.corners[tri, 1] + v * self.corners[tri, 2]
            n = self.normal[tri]
            wi = -d
            if material.is_emitter and n @ wi > 0.0 and self._light_pdf(tri) > 0.0:
                weight = 1.0
                if not prev_delta:
                    light = self._light_pdf(tri) * t * t / (n @ wi)
                    weight = prev_pdf**2 / (prev_pdf**2 + light**2)
                L = L + beta * weight * self._emission(tri)
            if self.max_depth >= 0 and depth + 1 >= self.max_depth:
                return L
            dim = CAMERA_DIMS + depth * DIMS_PER_BOUNCE
            albedo = np.array(material.albedo)
            if material.kind == "diffuse":
                s = n if n @ wi >= 0.0 else -n
                if len(self.emitters):
                    k = min(int(np.searchsorted(np.cumsum(self.select), uniform(key, dim), side="right")),
                            len(self.emitters) - 1)
                    ltri = self.emitters[k]
                    root = math.sqrt(uniform(key, dim + 1))
                    b2 = root * uniform(key, dim + 2)
                    b1 = root - b2
                    q = (1 - b1 - b2) * self.corners[ltri, 0] + b1 * self.corners[ltri, 1] + b2 * self.corners[ltri, 2]
                    to_light = q - p
                    dist = np.linalg.norm(to_light)
                    wo = to_light / dist
                    cos_l = -(self.normal[ltri] @ wo)
                    cos_o = s @ wo
                    if cos_l > 0.0 and cos_o > 0.0:
                        start = self._offset(p, n, wo)
                        shadow = q - start
                        length = np.linalg.norm(shadow)
                        if self._hit(start, shadow / length, length * (1.0 - SHADOW_EPSILON))[1] < 0:
                            light = self._light_pdf(ltri) * dist * dist / cos_l
                            bsdf = cos_o / math.pi
                            weight = light**2 / (light**2 + bsdf**2)
                            L = L + beta * albedo * bsdf / light * weight * self._emission(ltri)
                # cosine-weighted direction about s, same mapping and frame as the kernel
                u1, u2 = uniform(key, dim + 4), uniform(key, dim + 5)
                local = np.array([math.sqrt(u1) * math.cos(2 * math.pi * u2), math.sqrt(u1) * math.sin(2 * math.pi * u2),
                                  math.sqrt(max(0.0, 1.0 - u1))])
                sign = 1.0 if s[2] >= 0.0 else -1.0
                a = -1.0 / (sign + s[2])
                b = s[0] * s[1] * a
                tangent = np.array([1.0 + sign * s[0] ** 2 * a, sign * b, -sign * s[0]])
                bitangent = np.array([b, sign + s[1] ** 2 * a, -s[1]])
                d = local[0] * tangent + local[1] * bitangent + local[2] * s
                if s @ d <= 0.0:
                    return L
                beta = beta * albedo
                prev_pdf, prev_delta = (s @ d) / math.pi, False
            elif material.kind == "mirror":
                s = n if n @ wi >= 0.0 else -n
                d = -wi + 2.0 * (s @ wi) * s
                beta = beta * albedo
                prev_delta = True
            else:
                cos_i = n @ wi
                r, cos_t, eta_it, eta_ti = fresnel_dielectric(cos_i, material.ior)
                if uniform(key, dim + 3) <= r:
                    d = -wi + 2.0 * cos_i * n
                else:
                    d = -eta_ti * wi + (eta_ti * cos_i + cos_t) * n
                    beta = beta * albedo * eta_ti**2
                    eta *= eta_it
                prev_delta = True
            o = self._offset(p, n, d)
            depth += 1
            if beta.max() <= 0.0:
                return L
            if depth >= self.rr_depth:
                q = min(beta.max() * eta * eta, 0.95)
                if uniform(key, dim + 6) >= q:
                    return L
                beta = beta / q

    def pixel(self, i, j, spp, width, height, camera=None):
        """Mean radiance of pixel (column i, row j) over ``spp`` paths."""
        camera = camera or self.scene.camera
        total = np.zeros(3)
        for s in range(spp):
            key = np.uint64(sample_key(np.uint64(self.seed), j * width + i, s))
            d = pinhole_directions(camera, np.array([i + uniform(key, 0)]), np.array([j + uniform(key, 1)]),
                                   width, height)[0]
            total += self.radiance(np.array(camera.position, float), d, key)
        return total / spp
