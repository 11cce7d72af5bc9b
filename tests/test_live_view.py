"""``generate --view`` (gdbench.app.live_view): the scene reaches the viewer while the run trains,
every --view-every steps, and the run is the run it would be unwatched.

Oracles: the scenes the viewer was sent are the trainer's own at those steps (compared with the
parameters), and the watched run's parameters equal an unwatched run's bit for bit."""

from __future__ import annotations

import pytest
import torch

from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.densify import PARAM_NAMES
from gdbench.train.run import train
from tests._util import CAPTION, tiny, tiny_bank

pytest.importorskip("viser", reason="the viewer needs viser: pip install -e '.[view]' (or make setup)")


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank()})


def test_the_viewer_gets_the_trainers_scene_every_n_steps_and_the_run_is_unchanged(prior, tmp_path, monkeypatch):
    from gdbench.app import viewer as viewer_mod
    from gdbench.app.live_view import LiveView

    sent = []
    monkeypatch.setattr(viewer_mod.Viewer, "update_scene", lambda self, scene: sent.append(scene))
    live = LiveView(every=3, port=8097, verbose=False)
    steps = {}
    orig = live.__call__

    class Spy:  # the trainer's scene at each step the live view sees
        def __call__(self, state):
            if state.step % 3 == 0:
                steps[state.step] = state.scene().detach().clone()
            orig(state)

    try:
        watched = train(tiny("gd", tmp_path / "a", steps=9), prior, write_outputs=False, on_step=Spy())
    finally:
        live.close()
    assert live.viewer is not None and live.updates == len(sent) >= 1
    # each scene sent is the trainer's at one of the steps 3, 6, 9 (a newer copy may replace one waiting)
    for scene in sent:
        assert any(
            len(scene) == len(s) and torch.equal(scene.means, s.means) and torch.equal(scene.sh, s.sh)
            for s in steps.values()
        )
    plain = train(tiny("gd", tmp_path / "b", steps=9), prior, write_outputs=False)
    for k in PARAM_NAMES:
        assert torch.equal(watched.state.params[k], plain.state.params[k]), k


def test_view_every_must_be_a_positive_step_count():
    from gdbench.app.live_view import LiveView

    with pytest.raises(ValueError, match=r"view_every \(--view-every\): expected an int >= 1"):
        LiveView(every=0)
