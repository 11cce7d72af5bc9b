"""Mutation test: apply one plausible bug at a time to a copy of the project and check that the
tests of its area catch it (fail): the renderer (the renderer suite), and the wiring of the
paper's mechanisms into the trainer and the run folder's contract (the tests named per mutation).

    .venv/bin/python scripts/mutants.py [--only NAME ...] [--list]      (make mutants)

Each mutation replaces one exact snippet (it must occur exactly once, so a refactor that moves
the code makes this script fail loudly instead of testing nothing). C++ mutations rebuild the
extension in the copy (about a minute each). Exit code 0 when every mutation is caught.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TESTS = [
    "tests/test_sh.py",
    "tests/test_project.py",
    "tests/test_bin_tiles.py",
    "tests/test_composite.py",
    "tests/test_rasterize.py",
    "tests/test_gradcheck.py",
]
"""The renderer suite (the gsplat peer test is left out on purpose: the oracles must not need it)."""


@dataclass(frozen=True)
class Mutation:
    name: str
    file: str
    old: str
    new: str
    why: str
    area: str = "renderer"
    tests: tuple[str, ...] = tuple(TESTS)
    """Test files or node ids that must catch it (default: the renderer suite)."""


def _train(test: str) -> tuple[str, ...]:
    return (f"tests/test_train.py::{test}",)


MUTATIONS = [
    Mutation("sh-sign-degree-2", "renderers/splat/sh.py", "C2[1] * y * z", "-C2[1] * y * z",
             "flips the sign of one degree-2 basis function"),
    Mutation("sh-sign-degree-3", "renderers/splat/sh.py", "C3[5] * z * (xx - yy)", "C3[5] * z * (yy - xx)",
             "flips the sign of one degree-3 basis function"),
    Mutation("naive-det-torch", "renderers/splat/project.py",
             "det = (cross * cross).sum(-1) + eps2d * (a + c - eps2d)", "det = a * c - b * b",
             "det(Sigma') as a difference of two large numbers (torch projection)"),
    Mutation("naive-det-cpp", "renderers/splat/csrc/project_cpu.cpp",
             "L.det = (c0 * c0 + c1 * c1 + c2 * c2) + eps * (L.a + L.c - eps);", "L.det = L.a * L.c - L.b * L.b;",
             "det(Sigma') as a difference of two large numbers (C++ projection)"),
    Mutation("conic-b-sign", "renderers/splat/project.py", "conics = torch.stack([c / det, -b / det, a / det], dim=-1)",
             "conics = torch.stack([c / det, b / det, a / det], dim=-1)", "the off-diagonal conic term's sign"),
    Mutation("eps2d-one-axis", "renderers/splat/project.py", "c = (t2 * t2).sum(-1) + eps2d", "c = (t2 * t2).sum(-1)",
             "the 2D dilation added to one axis only"),
    Mutation("jacobian-clamp-off", "renderers/splat/project.py",
             "tx = zs * torch.clamp(x / zs, min=-(cx / fx + 0.3 * tan_fovx), max=(width - cx) / fx + 0.3 * tan_fovx)",
             "tx = x", "no tan-fov clamp of the Jacobian (x)"),
    Mutation("quat-unnormalised", "renderers/splat/project.py", "return quat_to_rotmat(normalize_quats(quats)) * scales[..., None, :]",
             "return quat_to_rotmat(quats) * scales[..., None, :]", "quaternions used without normalising"),
    Mutation("radius-3-sigma", "renderers/splat/project.py", "extend = torch.sqrt(2.0 * torch.log(ratio))",
             "extend = torch.full_like(ratio, 3.0)", "a fixed 3-sigma screen radius instead of the opacity-aware one"),
    Mutation("depth-sort-reversed", "renderers/splat/bin_tiles.py",
             "order = torch.sort(depths.reshape(-1)[ids], stable=True).indices",
             "order = torch.sort(depths.reshape(-1)[ids], stable=True, descending=True).indices",
             "tiles composited back to front"),
    Mutation("clamp-gradient-torch", "renderers/splat/composite.py", "return _ChunkState(dx, dy, G, alpha, unclamped & (alpha > 0), T, w, T_final)",
             "return _ChunkState(dx, dy, G, alpha, alpha > 0, T, w, T_final)",
             "the gradient let through the alpha_max clamp (torch compositor)"),
    Mutation("clamp-gradient-cpp", "renderers/splat/csrc/composite_cpu.cpp", "const M um = ok & unclamped;",
             "const M um = ok;", "the gradient let through the alpha_max clamp (C++ compositor)"),
    Mutation("early-stop-adds", "renderers/splat/composite.py", "kept = T_incl >= blend.t_min", "kept = T_incl >= 0",
             "no early termination at T < t_min (torch compositor)"),
    Mutation("early-stop-cpp", "renderers/splat/csrc/composite_cpu.cpp",
             "const M stop = ok & (nT < tmin), add = ok & ~stop;",
             "const M stop = ok & (nT < scalar_t(-1)), add = ok & ~stop;",
             "no early termination at T < t_min (C++ forward)"),
    Mutation("alpha-floor-off", "renderers/splat/composite.py",
             "alpha = torch.where(alpha >= blend.alpha_min, alpha, torch.zeros_like(alpha))", "",
             "Gaussians below alpha_min not skipped (torch compositor)"),
    Mutation("pixel-centre", "renderers/splat/project.py", "means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)",
             "means2d = torch.stack([fx * x / zs + cx - 0.5, fy * y / zs + cy - 0.5], dim=-1)",
             "pixel centres at integers instead of +0.5"),
    # the trainer's wiring of the paper's mechanisms (what reaches the renderers, captured by tests)
    Mutation("spread-dropped", "gdbench/train/views.py", "spread_deg=cfg.views.spread_deg,", "spread_deg=None,",
             "--views-spread-deg never reaches the step's cameras", "trainer wiring",
             _train("test_views_spread_reaches_the_noise_renderer")),
    Mutation("jitter-not-rendered", "gdbench/train/distill.py", "        means, log_scales = jitter(",
             "        _unused = jitter(", "the VGS jitter drawn but never reaching the render", "trainer wiring",
             _train("test_train_step_hands_the_renderer_the_jittered_gaussians_and_the_paired_views")),
    Mutation("run-redraws-every-step", "gdbench/mechanisms/noise.py",
             '    if redraw == "run":\n        return NoiseState(c, state.step + 1)\n    eps = randn(c.shape, generator=generator).to(c)',
             '    eps = randn(c.shape, generator=generator).to(c)\n    if redraw == "run":\n        return NoiseState(eps, state.step + 1)',
             "the noise colours redrawn every step although the redraw mode is 'run'", "trainer wiring",
             _train("test_train_step_redraws_the_noise_colours_as_configured")),
    Mutation("jitter-from-views-stream", "gdbench/train/distill.py", 'generator=state.streams["jitter"],',
             'generator=state.streams["views"],',
             "the VGS jitter drawing from the views stream, so presets stop seeing the same views", "trainer wiring",
             _train("test_presets_with_one_seed_draw_the_same_views_sigmas_and_iid_noise")),
    Mutation("ou-drift-decays", "gdbench/mechanisms/noise.py", "math.sqrt(1 - beta) * c + math.sqrt(beta) * eps",
             "(1 - beta) * c + math.sqrt(beta) * eps",
             "the OU redraw keeping (1 - beta) of the last colours, not sqrt(1 - beta): the field fades", "noise",
             _train("test_train_step_redraws_the_noise_colours_as_configured")),
    Mutation("variance-read-as-amplitude", "gdbench/mechanisms/noise.py",
             '    if mode == "variance":\n        return math.sqrt(ratio)', '    if mode == "variance":\n        return ratio',
             "the variance reading of the noise ratio computed as the amplitude reading", "noise",
             ("tests/test_noise.py",)),
    # the empirical prior off its default path
    Mutation("front-bias-wrong-views", "gdbench/priors/empirical.py",
             "az = np.concatenate([az_bank[i:j] for i, j in runs])", "az = az_bank[: sum(j - i for i, j in runs)]",
             "the front bias read at the bank's first views, not the view window's", "prior",
             ("tests/test_priors.py::test_the_prior_on_every_path_against_a_brute_force_posterior",)),
    Mutation("depth-zoom-inverted", "gdbench/priors/empirical.py",
             "zoom_images(torch.stack([cond.depth * a, a], -1), src, dst, H, W)",
             "zoom_images(torch.stack([cond.depth * a, a], -1), dst, src, H, W)",
             "the depth bank zoomed with the fov ratio inverted", "prior",
             ("tests/test_priors.py::test_the_prior_on_every_path_against_a_brute_force_posterior",)),
    # the metrics and the statistics
    Mutation("ssim-constants-unsquared", "gdbench/metrics/gt.py", "c1, c2 = 0.01**2, 0.03**2", "c1, c2 = 0.01, 0.03",
             "SSIM's stabilising constants not squared", "metrics",
             ("tests/test_views.py::test_gt_psnr_and_ssim_closed_forms",)),
    Mutation("bootstrap-90-percent", "gdbench/experiments/stats.py",
             "def bca_ci(d: np.ndarray, *, level: float = 0.95,", "def bca_ci(d: np.ndarray, *, level: float = 0.90,",
             "the claims' interval at 5/95 percentiles instead of 2.5/97.5", "metrics",
             ("tests/test_claims.py::test_the_statistics_against_independent_oracles",)),
    # the counter-based normal sampler (C++)
    Mutation("box-muller-u1-zero", "renderers/splat/csrc/normal_cpu.cpp",
             "(__builtin_convertvector((SI)(w1 >> 8), F) + 0.5f) * 5.9604644775390625e-8f",
             "__builtin_convertvector((SI)(w1 >> 8), F) * 5.9604644775390625e-8f",
             "Box-Muller's u1 allowed to be exactly 0 (a normal of 13 where the tail bound is 5.9)", "normal sampler",
             ("tests/test_rand.py::test_normals_at_2_25_draws_keep_the_tail_bound_and_the_law",)),
    # the run folder's contract
    Mutation("resume-ignores-a-result-field", "gdbench/train/checkpoint.py", '    {"out", "progress",',
             '    {"samples_per_step", "out", "progress",',
             "a result-changing field ignored by resume and the run id", "run folder",
             ("tests/test_train_identity.py::test_every_config_field_is_classified_and_result_fields_change_the_run_id",)),
    Mutation("outputs-after-lock", "gdbench/train/run.py",
             "        if write_outputs and state.step >= cfg.steps:\n            paths |= write_run_outputs(",
             "    if write_outputs and state.step >= cfg.steps:\n        paths |= write_run_outputs(",
             "the run's outputs written after its folder lock is released", "run folder",
             ("tests/test_train_identity.py::test_run_outputs_are_written_while_the_folder_lock_is_held",)),
]  # fmt: skip


def copy_project(dst: Path) -> None:
    files = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    files += subprocess.run(
        ["git", "ls-files", "--others", "--exclude-standard"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split()
    for f in files:
        src = ROOT / f
        if src.is_file():
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst / f)


def apply(root: Path, m: Mutation) -> None:
    path = root / m.file
    text = path.read_text()
    n = text.count(m.old)
    if n != 1:
        raise SystemExit(
            f"mutants: {m.name}: the snippet occurs {n} times in {m.file} (expected once); update the list"
        )
    path.write_text(text.replace(m.old, m.new))


def run_one(m: Mutation, python: str, timeout: int) -> tuple[bool, float, str]:
    with tempfile.TemporaryDirectory(prefix=f"mutant-{m.name}-") as tmp:
        root = Path(tmp)
        copy_project(root)
        apply(root, m)
        env = dict(
            os.environ,
            PYTHONPATH=str(root),
            GDBENCH_CACHE=os.environ.get("GDBENCH_CACHE", str(Path.home() / ".cache" / "gdbench")),
        )
        cmd = [python, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *m.tests]
        t0 = time.perf_counter()
        try:
            r = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=timeout)
            caught, tail = r.returncode != 0, (r.stdout + r.stderr).strip().splitlines()[-1:]
        except subprocess.TimeoutExpired:
            caught, tail = True, ["timed out (counted as caught)"]
        return caught, time.perf_counter() - t0, tail[0] if tail else ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", nargs="*", default=None, help="run only these mutations")
    ap.add_argument("--list", action="store_true", help="list the mutations and exit")
    ap.add_argument("--timeout", type=int, default=1200)
    args = ap.parse_args(argv)
    todo = [m for m in MUTATIONS if args.only is None or m.name in args.only]
    if args.list:
        for m in MUTATIONS:
            print(f"{m.name:30s} [{m.area}] {m.file}: {m.why}")
        return 0
    python = sys.executable
    survived = []
    print(f"mutants: {len(todo)} mutations, each against the tests of its area")
    for m in todo:
        caught, seconds, tail = run_one(m, python, args.timeout)
        status = "caught  " if caught else "SURVIVED"
        print(f"  {status} [{m.area}] {m.name:22s} ({seconds:5.0f} s) {m.why}: {tail}", flush=True)
        if not caught:
            survived.append(m.name)
    print(f"mutants: {len(todo) - len(survived)}/{len(todo)} caught" + (f"; survived: {survived}" if survived else ""))
    return 1 if survived else 0


if __name__ == "__main__":
    raise SystemExit(main())
