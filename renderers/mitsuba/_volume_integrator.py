"""The emission-absorption integrator of ``volume.py`` as a Mitsuba integrator.

Imports Mitsuba at module level (``@dr.syntax`` recompiles methods and needs module globals),
so import this module only after ``_lib.import_mitsuba()`` has set the variant.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


class GaussianVolumeIntegrator(mi.ad.integrators.common.RBIntegrator):
    """Ray marching through a Gaussian-mixture field with path-replay gradients.

    ``field(x) -> (rho, rho c)`` supplies the density and the premultiplied colour. The march
    runs ``steps`` jittered samples between the entry and exit of the box [lo, hi]; each step is
    a homogeneous segment: alpha = 1 - exp(-rho dt), emission alpha c. (alpha images come from a
    render with unit colour, which is exactly 1 - T.)
    """

    def __init__(self, props):
        super().__init__(props)
        self.steps = int(props.get("steps", 64))
        self.lo = mi.ScalarPoint3f(0.0)
        self.hi = mi.ScalarPoint3f(1.0)
        self.field = None

    @dr.syntax
    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        primal = mode == dr.ADMode.Primal
        ray = mi.Ray3f(dr.detach(ray))
        bbox = mi.BoundingBox3f(self.lo, self.hi)
        hit, t0, t1 = bbox.ray_intersect(ray)
        t0 = dr.maximum(t0, 0.0)
        active = mi.Bool(active) & hit & (t1 > t0)
        dt = (t1 - t0) / self.steps
        u = sampler.next_1d(active)
        L = mi.Spectrum(0.0 if primal else state_in)
        δL = mi.Spectrum(δL if δL is not None else 0)
        T = mi.Float(1.0)
        k = mi.UInt32(0)
        while dr.hint(active, max_iterations=self.steps, label="gaussian volume march"):
            x = ray(t0 + (mi.Float(k) + u) * dt)
            with dr.resume_grad(when=not primal):
                rho, rhoc = self.field(x)
                a = 1.0 - dr.exp(-rho * dt)
                c = rhoc / dr.maximum(rho, 1e-12)
                Le = T * a * c
                keep = 1.0 - a
            L[active] = (L + Le) if primal else (L - Le)
            with dr.resume_grad(when=not primal):
                if not primal:
                    # path replay: L now holds the radiance still to come behind this step
                    Lo = Le + L * keep / dr.detach(keep)
                    dr.backward_from(δL * dr.select(active & dr.isfinite(Lo), Lo, 0.0))
            T[active] = T * dr.detach(keep)
            k += 1
            active &= (k < self.steps) & (T > 1e-5)
        return L if primal else δL, True, [], L

    def to_string(self):
        return f"GaussianVolumeIntegrator[steps={self.steps}]"
