"""The end of a training step (gdbench/train/update.py and its Adam, adam.py): the trainer's Adam
against torch.optim's, the finiteness check, and the score's seeded backward."""

import io
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from gdbench.train.densify import PARAM_NAMES

ROOT = Path(__file__).resolve().parents[1]


def test_adam_gives_torch_optims_bits_and_checkpoints():
    """Oracle: torch.optim.Adam(fused=True). The trainer's Adam (adam.py) must give the same
    parameters and state bit for bit, over steps with changing learning rates, a group without a
    gradient, the first step (state made) and a row edit of the state as densification makes;
    and each one's state_dict must load into the other and go on with the same bits."""
    from gdbench.train.adam import Adam

    g = torch.Generator().manual_seed(3)
    shapes = {"means": (50, 3), "quats": (50, 4), "log_scales": (50, 3), "opacity_logits": (50,), "sh": (50, 1, 3),
              "sh_rest": (50, 3, 3)}  # fmt: skip

    def fresh(kind, lr=0.01):
        params = {k: torch.zeros(s).requires_grad_(True) for k, s in shapes.items()}
        groups = [{"params": [params[k]], "lr": lr * (i + 1), "name": k} for i, k in enumerate(PARAM_NAMES)]
        return params, (torch.optim.Adam(groups, eps=1e-15, fused=True) if kind == "torch" else Adam(groups, eps=1e-15))

    grads = [{k: torch.randn(s, generator=g) for k, s in shapes.items()} for _ in range(8)]

    def run(params, opt, steps):
        for step in steps:
            for k in PARAM_NAMES:
                params[k].grad = None if (step == 3 and k == "quats") else grads[step][k].clone()
            opt.param_groups[0]["lr"] = 0.05 / (step + 1)
            opt.step()
            if step == 4:  # densification's kind of edit: the moments of rows 0-9 dropped
                st = opt.state[params["sh"]]
                st["exp_avg"][:10] = 0
                st["exp_avg_sq"][:10] = 0

    def same(a, b):
        (pa, oa), (pb, ob) = a, b
        for k in PARAM_NAMES:
            assert torch.equal(pa[k], pb[k]) and not torch.equal(pa[k], torch.zeros(shapes[k]))
            for key in ("exp_avg", "exp_avg_sq", "step"):
                sa, sb = oa.state[pa[k]][key], ob.state[pb[k]][key]
                assert torch.equal(sa, sb) and sa.dtype == sb.dtype

    ref, ours = fresh("torch"), fresh("ours")
    run(*ref, range(5))
    run(*ours, range(5))
    same(ref, ours)

    # checkpoints cross over: each state_dict, through torch.save's format, into a fresh optimizer of
    # either kind, goes on as torch's own continuation does
    def restored(src, kind):
        buf = io.BytesIO()
        torch.save({"params": {k: v.detach() for k, v in src[0].items()}, "opt": src[1].state_dict()}, buf)
        blob = torch.load(io.BytesIO(buf.getvalue()), weights_only=True)
        params, opt = fresh(kind, lr=0.5)  # the learning rates come from the state_dict
        with torch.no_grad():
            for k in PARAM_NAMES:
                params[k].copy_(blob["params"][k])
        opt.load_state_dict(blob["opt"])
        run(params, opt, range(5, 8))
        return params, opt

    cont = restored(ref, "torch")
    for src, kind in ((ref, "ours"), (ours, "torch"), (ours, "ours")):
        same(cont, restored(src, kind))
    # a state dict of arithmetic this Adam does not compute is refused, naming the option; a step
    # saved as a number (torch's older format) loads as torch's float32 tensor
    for option in ("amsgrad", "maximize"):
        params = {k: torch.zeros(s).requires_grad_(True) for k, s in shapes.items()}
        other = torch.optim.Adam([{"params": [params[k]], "name": k} for k in PARAM_NAMES], **{option: True})
        with pytest.raises(ValueError, match=option):
            fresh("ours")[1].load_state_dict(other.state_dict())
    blob = ours[1].state_dict()
    for st in blob["state"].values():
        st["step"] = float(st["step"])
    params, opt = fresh("ours")
    opt.load_state_dict(blob)
    assert [(st["step"].dtype, float(st["step"])) for st in opt.state.values()] == [
        (torch.float32, float(st["step"])) for st in ours[1].state.values()
    ]


def test_finiteness_check_finds_each_kind_and_changes_nothing():
    """Oracle: torch.isfinite per tensor; the values after the check are bit-identical."""
    from gdbench.train.update import _all_finite

    g = torch.Generator().manual_seed(4)
    tensors = [torch.randn(7, 3, generator=g), torch.randn(5, generator=g) * 1e38, torch.randn(2, 2, generator=g)]
    before = [t.clone() for t in tensors]
    assert _all_finite(tensors) and all(torch.equal(a, b) for a, b in zip(tensors, before))
    for i, bad in ((0, float("nan")), (1, float("inf")), (2, -float("inf"))):
        t = [x.clone() for x in before]
        t[i].view(-1)[1] = bad
        assert not _all_finite(t)
    assert _all_finite([])


def test_the_seeded_backward_gives_x_backwards_bits_without_importing_sympy():
    """Oracle: ``x.backward(g)`` (leaf gradients bit for bit, under no_grad too); a training process
    never imports torch's symbolic shapes (sympy, 0.4 s), as that call's shape check would."""
    from gdbench.train.update import _backward

    g = torch.Generator().manual_seed(5)
    w, a = torch.randn(6, 4, generator=g, requires_grad=True), torch.randn(3, 6, generator=g)
    seed = torch.randn(3, 4, generator=g)
    (a @ w.tanh()).backward(seed)
    want, w.grad, x = w.grad, None, a @ w.tanh()
    with torch.no_grad():
        _backward(x, seed)
    assert torch.equal(w.grad, want) and want.abs().sum() > 0
    with pytest.raises(ValueError, match="grad: expected the shape of x"):
        _backward(a @ w.tanh(), seed.T)
    code = "import sys; from tests._util import CAPTION, tiny, tiny_bank; "
    code += "from gdbench.priors.empirical import EmpiricalPrior; "
    code += "from gdbench.train.trainer import init_state, make_context, train_step; "
    code += "ctx = make_context(tiny(), EmpiricalPrior(banks={CAPTION: "
    code += "tiny_bank(CAPTION)})); st = init_state(ctx); [train_step(st, ctx) for _ in range(2)]; "
    code += "print('torch.fx.experimental.symbolic_shapes' in sys.modules, st.step)"
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert run.returncode == 0 and run.stdout.split() == ["False", "2"], run.stderr[-2000:]


def test_a_missing_private_api_is_one_line_naming_it(monkeypatch):
    """gdbench.core.private: the private torch and Python functions gdbench calls are the real
    ones where they exist, and a missing one raises one line naming it and what it was for."""
    import threading

    from gdbench.core import private

    assert private.fused_adam_ is torch._fused_adam_ and private.shutdown_threads is threading._shutdown
    monkeypatch.delattr(torch, "_fused_adam_")
    stub = private._guarded(torch, "_fused_adam_", "the trainer's Adam step")
    with pytest.raises(RuntimeError, match=r"torch\._fused_adam_ is missing in torch .* \(the trainer's Adam step\)"):
        stub([], [])
