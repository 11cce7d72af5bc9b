"""A/B of two builds of the C++ extension in one process: the only timing on this shared 2-core
machine that holds steady (absolute figures swing by 2x between hours; interleaved builds see
the same phase). Checks that both builds give the same bits, then times the cases in rounds,
alternating builds.

    .venv/bin/python scripts/ab_ext.py --a HEAD --b .                  # working tree vs HEAD
    .venv/bin/python scripts/ab_ext.py --a . --b . --b-flags=-DFOO=1   # a compile-time variant
    .venv/bin/python scripts/ab_ext.py --params state.pt               # plus a trainer's scene
    .venv/bin/python scripts/ab_ext.py --train-step 300 --params state.pt --step 1500

``--train-step K`` also times the gd preset's whole training step, the builds alternating
every 25 steps on one running state (the builds give the same bits or gradients equal to
summation order, so both see the same run): from ``--params`` at ``--step``, or from the
initial scene after K warm-up steps.

``--trainer REV`` builds nothing: it times the training step of ``gdbench/train`` at REV (a)
against the working tree's (b), the same way (only that package differs between the sides; the
rest of gdbench is the working tree's):

    .venv/bin/python scripts/ab_ext.py --trainer HEAD --params state.pt --step 1500

Besides random clouds, the cases include the training step's noise pass (the gd preset's noise
cloud at 64 px: rgb and weight_sq) and, with ``--params``, a trainer's Gaussians (a torch file
of its ``state.params``: means, quats, log_scales, opacity_logits, sh) at 64 px.

A build is a git revision (its ``renderers/splat/csrc``) or ``.`` (the working tree's), compiled
with the working tree's CFLAGS (``renderers/splat/_ext.py``) plus the given flags.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gdbench.refcheck.bm_render import _camera, random_cloud  # noqa: E402
from renderers.splat import _ext, rasterize  # noqa: E402

CASES = ((10000, 256), (3000, 64), (1000, 64))


def build(rev: str, flags: list[str], tag: str, work: Path):
    src = work / f"src_{tag}"
    src.mkdir()
    if rev == ".":
        for p in _ext.CSRC.iterdir():
            (src / p.name).write_bytes(p.read_bytes())
    else:
        cmd = ["git", "-C", str(ROOT), "archive", rev, "renderers/splat/csrc"]
        tar = subprocess.run(cmd, check=True, capture_output=True)
        subprocess.run(["tar", "-x", "-C", str(src), "--strip-components=3"], input=tar.stdout, check=True)
    out = work / f"build_{tag}"
    out.mkdir()
    print(f"building {tag}: {rev} {' '.join(flags)}", flush=True)
    return _ext.compile_sources(f"gdbench_ab_{tag}", out, csrc=src, extra_cflags=tuple(flags))


def scene(n: int, dtype=torch.float32) -> dict:
    return {k: v.to(dtype).clone().requires_grad_(True) for k, v in random_cloud(n).items()}


def noise_scene(dtype=torch.float32) -> dict:
    """The gd preset's noise cloud with one draw of colours (rendered with weight_sq)."""
    from gdbench.mechanisms.noise import NoiseConfig, make_noise_cloud

    g = torch.Generator().manual_seed(0)
    c = make_noise_cloud(NoiseConfig(), 3, generator=g)
    s = {"means": c.means, "quats": c.quats, "scales": c.scales, "opacities": c.opacities,
         "colors": torch.randn(len(c), 3, generator=g)}  # fmt: skip
    return {k: v.to(dtype).clone().requires_grad_(True) for k, v in s.items()} | {"weight_sq": True}


def params_scene(path: Path, dtype=torch.float32) -> dict:
    """A trainer's parameters (``state.params``), activated as the trainer renders them."""
    from renderers.splat.sh import C0

    p = torch.load(path)
    s = {"means": p["means"], "quats": p["quats"], "scales": p["log_scales"].exp(),
         "opacities": torch.sigmoid(p["opacity_logits"]), "colors": C0 * p["sh"][:, 0] + 0.5}  # fmt: skip
    return {k: v.detach().to(dtype).clone().requires_grad_(True) for k, v in s.items()}


def render(s: dict, res: int, backward: bool):
    cam = _camera(res, "cpu")
    dt = s["means"].dtype
    extra = ("weight_sq",) if s.get("weight_sq") else ()
    with torch.set_grad_enabled(backward):
        out = rasterize(
            s["means"], s["quats"], s["scales"], s["opacities"], s["colors"],
            cam.viewmats.to(dt), cam.Ks.to(dt), res, res, outputs=("rgb", "alpha", "depth") + extra, check_values=False,
        )  # fmt: skip
        if backward:
            w = torch.linspace(0, 1, out.rgb.numel(), dtype=dt).reshape(out.rgb.shape)
            (out.rgb * w).sum().backward()
    return out


def best_of(s: dict, px: int, backward: bool, repeats: int = 5) -> float:
    render(s, px, backward)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        render(s, px, backward)
        ts.append(time.perf_counter() - t)
    return min(ts)


def cases(dtype, params: Path | None) -> list[tuple[str, dict, int]]:
    out = [(f"{n} random", scene(n, dtype), px) for n, px in CASES] + [("gd noise cloud", noise_scene(dtype), 64)]
    return out + ([(f"{params.name}", params_scene(params, dtype), 64)] if params is not None else [])


def use(module) -> None:
    _ext._STATE["module"] = module


def same_bits(mods: dict, params: Path | None) -> bool:
    """Whether both builds give the same bits; where not, prints the largest difference of each
    differing output relative to its largest magnitude."""
    results = {}
    for tag, mod in mods.items():
        use(mod)
        res = {}
        for dt in (torch.float32, torch.float64):
            for name, s, px in cases(dt, params):
                out = render(s, px, True)
                for field, x in out._asdict().items():
                    if x is not None:
                        res[(str(dt)[6:], name, field)] = x.detach()
                res |= {(str(dt)[6:], name, f"grad {k}"): s[k].grad for k in s if k != "weight_sq"}
        results[tag] = res
    a, b = results.values()
    differ = [key for key, x in a.items() if not torch.equal(x, b[key])]
    for key in differ:
        d = (a[key].double() - b[key].double()).abs().max() / a[key].double().abs().max().clamp_min(1e-300)
        print(f"  differs: {' '.join(key)} (max |a - b| / max |a| = {float(d):.2e})")
    return not differ


def train_step_ab(sides: dict, params: Path | None, step: int, warmup: int, rounds: int) -> None:
    """Times the gd preset's training step with ``sides`` {"a": f, "b": f}, each f(state, ctx)
    running one step its way, alternating every 25 steps on one running state."""
    from gdbench.train import trainer as T
    from gdbench.train.config import preset

    cfg = preset("gd", progress=False)
    ctx = T.make_context(cfg)
    st = T.init_state(ctx)
    if params is not None:
        p = torch.load(params)
        st.params = {k: v.detach().clone().requires_grad_(True) for k, v in p.items()}
        st.optimizer = T._optimizer(st.params, cfg)
        st.densify = ctx.strategy.init_state(st.params["means"].shape[0])
        st.step = step
    for i in range(warmup):
        sides["ab"[i % 2]](st, ctx)
    times: dict[str, list[float]] = {"a": [], "b": []}
    for _ in range(3 * rounds):
        for tag, f in sides.items():
            times[tag] += [f(st, ctx)["seconds"] for _ in range(25)]
    a, b = statistics.median(times["a"]), statistics.median(times["b"])
    n = st.params["means"].shape[0]
    print(f"training step (gd, steps {st.step - 150 * rounds}-{st.step}, {n} Gaussians at the end): "
          f"a {a * 1e3:.2f} ms  b {b * 1e3:.2f} ms  b/a {b / a:.3f}")  # fmt: skip


def build_steps(mods: dict) -> dict:
    """Step functions for two builds of the extension (the working tree's trainer)."""
    from gdbench.train import trainer as T

    def side(mod):
        def f(st, ctx):
            use(mod)
            return T.train_step(st, ctx)

        return f

    return {tag: side(mod) for tag, mod in mods.items()}


def trainer_at(rev: str):
    """The training step's modules (``gdbench/train/*.py``) at git revision ``rev``, imported as a
    second package (``gdbench.train_ab``) beside the working tree's; returns its ``trainer``."""
    import importlib
    import importlib.util

    tmp = Path(tempfile.mkdtemp(prefix="trainer-ab-"))
    tiers = subprocess.run(["git", "-C", str(ROOT), "cat-file", "-e", f"{rev}:gdbench/core/__init__.py"],
                           capture_output=True)  # fmt: skip
    if tiers.returncode != 0:
        raise SystemExit(f"--trainer: {rev} predates the package in tiers (a5ace9c): its trainer imports modules "
                         "that moved; A/B two revisions of one layout")  # fmt: skip
    files = subprocess.run(["git", "-C", str(ROOT), "ls-tree", "--name-only", rev, "gdbench/train/"],
                           check=True, capture_output=True, text=True).stdout.split()  # fmt: skip
    for f in files:
        if f.endswith(".py"):
            src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{f}"], check=True, capture_output=True)
            # its own modules from the copy: the imports are absolute (gdbench.train.x)
            text = src.stdout.decode().replace("gdbench.train.", "gdbench.train_ab.")
            (tmp / Path(f).name).write_text(text)
    name = "gdbench.train_ab"
    spec = importlib.util.spec_from_file_location(name, tmp / "__init__.py", submodule_search_locations=[str(tmp)])
    pkg = importlib.util.module_from_spec(spec)
    sys.modules[name] = pkg  # dataclasses look their module up here
    spec.loader.exec_module(pkg)
    return importlib.import_module(f"{name}.trainer")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--a", default="HEAD", help="git revision or '.' (working tree)")
    ap.add_argument("--b", default=".")
    ap.add_argument("--a-flags", default="", help="extra compiler flags, space-separated")
    ap.add_argument("--b-flags", default="")
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--params", type=Path, default=None, help="a torch file of a trainer's state.params")
    ap.add_argument("--only", default="", help="time only the cases whose 'name N px' contains this (e.g. '64 px')")
    ap.add_argument(
        "--train-step", type=int, default=None, metavar="K", help="also A/B the training step (K warm-up steps)"
    )
    ap.add_argument("--step", type=int, default=1500, help="the step count of --params for --train-step")
    ap.add_argument(
        "--trainer", default=None, metavar="REV",
        help="instead: A/B the training step of gdbench/train at REV (a) against the working tree's (b)",
    )  # fmt: skip
    args = ap.parse_args()
    if args.trainer is not None:
        from gdbench.train import trainer as T

        old = trainer_at(args.trainer)
        sides = {"a": old.train_step, "b": T.train_step}
        train_step_ab(sides, args.params, args.step, args.train_step or 100, max(args.rounds, 1))
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        mods = {
            "a": build(args.a, args.a_flags.split(), "a", Path(tmp)),
            "b": build(args.b, args.b_flags.split(), "b", Path(tmp)),
        }
        print("same bits (forward and gradients, float32 and float64):", same_bits(mods, args.params))
        todo = [c for c in cases(torch.float32, args.params) if args.only in f"{c[0]} {c[2]} px"]
        times: dict[tuple, list[float]] = {}
        for _ in range(args.rounds):
            for tag, mod in mods.items():
                use(mod)
                for name, s, px in todo:
                    for backward in (False, True):
                        times.setdefault((name, backward, tag), []).append(best_of(s, px, backward))
        for name, _, px in todo if args.rounds > 0 else ():
            for backward in (False, True):
                a = statistics.median(times[(name, backward, "a")])
                b = statistics.median(times[(name, backward, "b")])
                mode = "fwd+bwd" if backward else "fwd"
                print(f"{name:>16s} {px:>4d} {mode:8s} a {a * 1e3:8.2f} ms  b {b * 1e3:8.2f} ms  b/a {b / a:.3f}")
        if args.train_step is not None:
            train_step_ab(build_steps(mods), args.params, args.step, args.train_step, max(args.rounds, 1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
