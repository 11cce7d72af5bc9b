"""The trainer's run identity and run folder: which config fields name a run (every field
classified), the folder lock held while outputs are written, one save per checkpoint, and one
thread training the two-thread run bit for bit."""

import dataclasses

import pytest
import torch

from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.config import TrainConfig, preset
from gdbench.train.run import train
from gdbench.train.trainer import init_state, make_context, train_step
from tests._util import CAPTION, tiny, tiny_bank


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


def test_run_id_keeps_runs_made_before_a_field_was_added():
    """A field added later (views_spread_deg) is left out of the run's id at the value that behaves
    as the code did before it, so a finished run of the older code keeps its id (a sweep finds it
    finished instead of refusing to overwrite it); any other value changes the id."""
    from gdbench.core.io import sha256_json
    from gdbench.train.checkpoint import ADDED_AT_DEFAULT, RESUME_IGNORES
    from gdbench.train.layout import flat_config
    from gdbench.train.run import config_dict, run_id

    cfg = preset("gd", steps=50)
    flat = flat_config(config_dict(cfg))  # the layout run ids were first computed in
    before = {k: v for k, v in flat.items() if k not in RESUME_IGNORES and k not in ADDED_AT_DEFAULT}
    for key in ADDED_AT_DEFAULT:  # nested ones (noise.source, densify.min_every) by their dotted keys
        group, _, name = key.rpartition(".")
        if group:
            before[group] = {k: v for k, v in before[group].items() if k != name}
    assert "noise.source" in ADDED_AT_DEFAULT and "source" in flat["noise"]
    assert "densify.min_every" in ADDED_AT_DEFAULT and "min_every" in flat["densify"]
    assert run_id(cfg) == sha256_json(before)[:16]
    assert run_id(preset("gd", steps=50, views_per_step=4, views_spread_deg=10.0)) != run_id(
        preset("gd", steps=50, views_per_step=4)
    )
    assert run_id(preset("gd", steps=50, **{"noise.source": "pose"})) != run_id(cfg)  # any other value counts


def _changed(cfg, name):
    """``cfg`` (a config dataclass) with field ``name`` set to another valid value (of its type, or
    another choice of its Literal), for the field classification test."""
    import typing
    from pathlib import Path

    v = getattr(cfg, name)
    hint = typing.get_type_hints(type(cfg))[name]
    choices = [a for a in typing.get_args(hint) if isinstance(a, str)]
    special = {
        "spread_deg": 10.0,
        "variants": 3,
        "init_ply": Path("cloud.ply"),
        "log_dir": Path("tb"),
        "sd_controlnet": "controlnet",
        "init": "bank-depth",
        "guidance": "sds",  # a method's name: built-in ones, or a reference to the user's
        "source": "pose",
    }
    if name in special:
        new = special[name]
    elif isinstance(v, bool):
        new = not v
    elif isinstance(v, int):
        new = v + 1
    elif isinstance(v, float):
        new = v * 1.5 + 0.01
    elif choices:
        new = next(c for c in choices if c != v)
    elif isinstance(v, str):
        new = v + " x" if name != "learned_model" else "front"
    elif isinstance(v, tuple):
        new = (v[0] + 0.5 if v[0] < v[-1] else v[0] - 0.1, *v[1:])
    elif isinstance(v, Path):
        new = v / "other"
    elif dataclasses.is_dataclass(v):
        f = next(f for f in dataclasses.fields(v) if type(getattr(v, f.name)) in (int, float))
        new = _changed(v, f.name)  # another valid value of its first number
    else:
        raise AssertionError(f"no change rule for {name} = {v!r}")
    return dataclasses.replace(cfg, **{name: new})


IGNORED_FIELDS = {"out", "progress", "checkpoint_every", "log_every", "turntable_frames", "log_dir", "device"}
"""The only TrainConfig fields that cannot change a run's result (where it is written, how it
reports, how often it checkpoints, where its TensorBoard scalars go; the turntable is drawn after
training), and the device (float rounding only, as the thread count; recorded in run.json)."""
RESULT_FIELDS = {
    "prompt", "preset", "steps", "seed", "resolution", "views", "init", "init_points", "init_ply", "init_opacity",
    "init_color", "camera_radius", "fovy_range", "azimuth_range", "elevation_range", "background", "guidance",
    "sigma_min", "sigma_max", "anneal", "samples_per_step", "weight", "prior",
    "noise", "vgs", "optim", "densify", "sh_degree", "max_bad_steps",
}  # fmt: skip
"""Fields that may change a result (or, as preset and max_bad_steps, say which run it is)."""


def test_every_config_field_is_classified_and_result_fields_change_the_run_id():
    """The run-folder contract over every TrainConfig field, against this test's own explicit
    lists (not the code's): a field that may change a result changes the run id and resume names
    it as a difference (so a checkpoint of the other value is refused); only the listed others
    leave both alone. A field added to TrainConfig fails here until it is put in one list."""

    from gdbench.train.checkpoint import RESUME_IGNORES, config_diff
    from gdbench.train.run import config_dict, run_id

    names = {f.name for f in dataclasses.fields(TrainConfig)}
    assert not RESULT_FIELDS & IGNORED_FIELDS
    assert names == RESULT_FIELDS | IGNORED_FIELDS, f"classify: {sorted(names - RESULT_FIELDS - IGNORED_FIELDS)}"
    assert RESUME_IGNORES == IGNORED_FIELDS
    base = preset("gd", steps=50)
    changes = [(base, _changed(base, name), name) for name in sorted(names - {"views", "vgs", "prior"})]
    # the groups that were flat fields (views, vgs) and every prior's settings, one by one, under the
    # names run ids and resume compare them by (the flat layout: views_per_step, vgs_gamma, sd_model)
    from gdbench.core.constraints import flag
    from gdbench.priors.factory import PRIOR_CONFIGS

    for group in ("views", "vgs"):
        sub = getattr(base, group)
        for f in dataclasses.fields(sub):
            other = dataclasses.replace(base, **{group: _changed(sub, f.name)})
            changes.append((base, other, flag(f"{group}.{f.name}")[2:].replace("-", "_")))
    # the structured noise's switch, a noise field that was a flat one (structured_noise)
    changes.append((base, dataclasses.replace(base, noise=_changed(base.noise, "enabled")), "structured_noise"))
    for kind in PRIOR_CONFIGS:
        b = preset("gd", steps=50, prior=kind)
        changes += [
            (b, dataclasses.replace(b, prior=_changed(b.prior, f.name)), f.name) for f in dataclasses.fields(b.prior)
        ]
        if kind != "empirical":
            changes.append((base, b, "prior"))
    assert len(changes) > 45  # not vacuous
    for a, b, name in changes:
        if name in IGNORED_FIELDS:
            assert run_id(b) == run_id(a), name
            assert config_diff(config_dict(a), config_dict(b)) == [], name
        else:
            assert run_id(b) != run_id(a), name
            assert config_diff(config_dict(a), config_dict(b)) == [name], name


def test_run_outputs_are_written_while_the_folder_lock_is_held(prior, tmp_path, monkeypatch):
    """Every output of a run (the checkpoint, scene.ply, the turntable, the curves, run.json) is
    written while the run holds its folder's lock: checked from inside each write, where taking
    the lock from another file handle must fail (a run that released it first could have its
    folder claimed by a second run halfway through)."""
    import gdbench.core.turntable as turntable
    import gdbench.train.run as run_mod
    from gdbench.core.io import FolderBusy, FolderLock
    from gdbench.core.scene import GaussianScene

    out = tmp_path / "run"
    held = {}

    def probe(name, fn):
        def wrapped(*args, **kw):
            try:
                with FolderLock(out):
                    held[name] = False
            except FolderBusy:
                held[name] = True
            return fn(*args, **kw)

        return wrapped

    monkeypatch.setattr(run_mod, "save_checkpoint", probe("checkpoint", run_mod.save_checkpoint))
    monkeypatch.setattr(run_mod, "write_json", probe("run.json", run_mod.write_json))
    monkeypatch.setattr(run_mod, "write_curves", probe("curves", run_mod.write_curves))
    monkeypatch.setattr(turntable, "write_turntable", probe("turntable", turntable.write_turntable))
    monkeypatch.setattr(GaussianScene, "save_ply", probe("scene.ply", GaussianScene.save_ply))
    r = train(tiny("gd", steps=4, out=out), prior)
    assert (out / "run.json").is_file() and r.state.step == 4
    assert held == dict.fromkeys(("checkpoint", "scene.ply", "turntable", "curves", "run.json"), True), held
    with FolderLock(out):  # and released at the end
        pass


@pytest.mark.parametrize(("steps", "saved"), [(4, [2, 4]), (5, [2, 4, 5])])
def test_a_run_saves_each_checkpoint_once(prior, tmp_path, monkeypatch, steps, saved):
    """Every checkpoint_every steps, and at the end unless the last step was just saved (the same
    state twice cost an fsync'ed write); the file holds the last step either way."""
    import gdbench.train.run as run_mod
    from gdbench.train.checkpoint import checkpoint_path

    seen = []
    save = run_mod.save_checkpoint

    def counted(state, ctx, path):
        seen.append(state.step)
        return save(state, ctx, path)

    monkeypatch.setattr(run_mod, "save_checkpoint", counted)
    cfg = tiny("gd", steps=steps, out=tmp_path / "run")  # checkpoint_every=2
    train(cfg, prior)
    assert seen == saved
    assert torch.load(checkpoint_path(cfg), weights_only=False)["step"] == steps


def test_one_thread_trains_the_two_thread_run_bit_for_bit(tmp_path):
    """The empirical prior's run on one thread (a sweep's worker on two cores) gives the two-thread
    run's parameters: the compositor's backward sums in at least two chunks, and nothing else of
    a step groups its sums by thread count (docs/conventions.md). 32 px: four tiles per view."""

    cfg = preset("gd", steps=20, densify_every=5, resolution=32, init_points=600, out=tmp_path, progress=False)
    ctx = make_context(cfg)
    params, before = {}, torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            state = init_state(ctx)
            for _ in range(20):
                train_step(state, ctx)
            params[threads] = {k: v.detach() for k, v in state.params.items()}
    finally:
        torch.set_num_threads(before)
    assert params[1]["means"].shape[0] != 600  # densification ran
    for k in params[1]:
        assert torch.equal(params[1][k], params[2][k]), k
