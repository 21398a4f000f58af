"""The input loop's path tracer: Mitsuba's ``path`` integrator, step for step, that also hands back the
primary hit, so a camera ray is traced once for its radiance and its features.

``trace(mi, scene, sampler, ray, max_depth, rr_depth) -> (radiance, valid, primary)`` follows
``src/integrators/path.cpp`` of Mitsuba 3.9 (``hide_emitters`` false, unpolarised RGB): the same
loop state, the same calls in the same order and the same sampler draws a bounce (emitter 2, BSDF
1 + 2, Russian roulette 1, drawn whether or not roulette applies). Fed the same sampler state, it
gives the per-sample values of ``scene.integrator().sample`` bit for bit on the LLVM backend
(``tests/test_render.py`` checks that on every sample of a frame). ``primary``: ``hit`` (Bool),
``p`` (Point3f), ``n`` (shading normal), ``t`` (ray distance), ``shape`` (registry id, UInt32, 0 on
a miss) and ``albedo`` (``eval_diffuse_reflectance``) of the camera ray's first hit, recorded in the
loop's first iteration (the interaction the integrator computes there anyway).

Why not ``integrator.sample``: it has no way to return its first interaction, so the features needed a
second ``scene.ray_intersect`` of every camera ray (4-6% of the input loop on the CPU, docs/throughput.md).
"""
from __future__ import annotations


def mis_weight(dr, pdf_a, pdf_b):
    """The power heuristic, as ``path.cpp``: ``a^2 / (a^2 + b^2)``, 0 where that is not finite."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    w = a2 / (a2 + b2)
    return dr.select(dr.isfinite(w), w, 0.0)


def trace(mi, scene, sampler, ray, max_depth: int, rr_depth: int):
    """Radiance (Color3f, not yet times the ray weight), validity (Bool) and the primary hit (dict)
    of camera rays ``ray``; ``sampler`` continues from where the ray's own draws left it."""
    import drjit as dr
    Float, UInt32 = mi.Float, mi.UInt32
    env = scene.environment() is not None
    ray = mi.Ray3f(ray)
    pi = scene.ray_intersect_preliminary(ray, True, False, 0, 0, mi.Bool(True))
    state = (mi.Bool(True), ray, pi, mi.Spectrum(1.0), mi.Spectrum(0.0), Float(1.0), UInt32(0), mi.Bool(env),
             dr.zeros(mi.Interaction3f), Float(1.0), mi.Bool(True), sampler,
             mi.Bool(False), mi.Point3f(0.0), mi.Vector3f(0.0), Float(0.0), UInt32(0), mi.Color3f(0.0))

    def body(*s):
        return _bounce(mi, dr, scene, int(max_depth), int(rr_depth), *s)

    out = dr.while_loop(state, lambda active, *_: active, body, labels=_LABELS, label="primary_path")
    (_a, _r, _pi, _thr, result, _eta, _d, valid, _psi, _pdf, _delta, _smp,
     hit, p, n, t, shape, albedo) = out
    primary = dict(hit=hit, p=p, n=n, t=t, shape=shape, albedo=albedo)
    return dr.select(valid, result, 0.0), valid, primary


_LABELS = ("active", "ray", "pi", "throughput", "result", "eta", "depth", "valid_ray", "prev_si",
           "prev_bsdf_pdf", "prev_bsdf_delta", "sampler", "hit", "p", "n", "t", "shape", "albedo")


def _bounce(mi, dr, scene, max_depth, rr_depth, active, ray, pi, throughput, result, eta, depth, valid_ray,
            prev_si, prev_bsdf_pdf, prev_bsdf_delta, sampler, hit, p, n, t, shape, albedo):
    """One iteration of ``path.cpp``'s loop (its comments' section names), plus the first-hit record."""
    Flags = mi.BSDFFlags
    si = pi.compute_surface_interaction(ray, mi.RayFlags.All)
    # direct emission, MIS-weighted against the previous bounce's BSDF sample
    ds = mi.DirectionSample3f(scene, si, prev_si)
    em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_bsdf_delta)
    mis_bsdf = mis_weight(dr, prev_bsdf_pdf, em_pdf)
    result = dr.fma(throughput, ds.emitter.eval(si, prev_bsdf_pdf > 0.0) * mis_bsdf, result)
    active_next = (depth + 1 < max_depth) & si.is_valid()
    bsdf = si.bsdf(ray)
    # the first hit: what the features need (this iteration's interaction, so no second trace)
    first = depth == 0
    hit = dr.select(first, si.is_valid(), hit)
    p, n, t = dr.select(first, si.p, p), dr.select(first, si.sh_frame.n, n), dr.select(first, si.t, t)
    sid = dr.select(si.is_valid(), dr.reinterpret_array(mi.UInt32, si.shape), 0)
    shape = dr.select(first, sid, shape)
    albedo = dr.select(first, bsdf.eval_diffuse_reflectance(si, first & si.is_valid()), albedo)
    # emitter sampling
    active_em = active_next & mi.has_flag(bsdf.flags(), Flags.Smooth)
    ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
    active_em &= ds.pdf != 0.0
    wo = si.to_local(ds.d)
    # evaluate BSDF * cos(theta) and sample a direction
    sample_1 = sampler.next_1d()
    sample_2 = sampler.next_2d()
    bsdf_val, bsdf_pdf, bsdf_sample, bsdf_weight = bsdf.eval_pdf_sample(mi.BSDFContext(), si, wo, sample_1, sample_2)
    mis_em = dr.select(ds.delta, 1.0, mis_weight(dr, ds.pdf, bsdf_pdf))
    result = dr.select(active_em, dr.fma(throughput, bsdf_val * em_weight * mis_em, result), result)
    # BSDF sampling and the loop variables
    ray = si.spawn_ray(si.to_world(bsdf_sample.wo))
    throughput = throughput * bsdf_weight
    eta = eta * bsdf_sample.eta
    valid_ray |= active & si.is_valid() & ~mi.has_flag(bsdf_sample.sampled_type, Flags.Null)
    prev_si = mi.Interaction3f(si)
    prev_bsdf_pdf = bsdf_sample.pdf
    prev_bsdf_delta = mi.has_flag(bsdf_sample.sampled_type, Flags.Delta)
    # stopping criterion (Russian roulette draws its sample at every bounce, as path.cpp)
    depth = dr.select(si.is_valid(), depth + 1, depth)
    throughput_max = dr.max(throughput)
    rr_prob = dr.minimum(throughput_max * dr.square(eta), 0.95)
    rr_active = depth >= rr_depth
    rr_continue = sampler.next_1d() < rr_prob
    throughput = dr.select(rr_active, throughput * dr.rcp(rr_prob), throughput)
    active = active_next & (~rr_active | rr_continue) & (throughput_max != 0.0)
    pi = scene.ray_intersect_preliminary(ray, False, dr.flag(dr.JitFlag.SymbolicLoops), 0, 0, active)
    return (active, ray, pi, throughput, result, eta, depth, valid_ray, prev_si, prev_bsdf_pdf, prev_bsdf_delta,
            sampler, hit, p, n, t, shape, albedo)
