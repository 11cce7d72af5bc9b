"""scripts/train_world64.sh's distillation stage: it refuses to start before both teachers have
finished, and otherwise renders (or finds) the data, then launches one student per teacher from a
clone at one commit, each with its teacher's weights, the guidance and the schedule (the python it
runs is a stub that records its arguments). Runs of other clones on the machine are not its own."""

import subprocess
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "train_world64.sh"


def _run(*args, env=None):
    return subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, env=env, timeout=120)


def test_distil_waits_for_both_teachers_then_starts_one_student_each(tmp_path):
    import os

    teachers = tmp_path / "teachers"
    (teachers / "runs" / "prior-world64p4-uniform").mkdir(parents=True)
    (teachers / "runs" / "prior-world64p4-uniform" / "model.safetensors").write_bytes(b"x")
    got = _run("distil", str(tmp_path / "students"), str(teachers))
    assert got.returncode == 2
    assert "no finished teacher at" in got.stderr and "prior-world64p4-front/model.safetensors" in got.stderr
    assert not (tmp_path / "students").exists()  # nothing cloned before the teachers are there

    (teachers / "runs" / "prior-world64p4-front").mkdir(parents=True)
    (teachers / "runs" / "prior-world64p4-front" / "model.safetensors").write_bytes(b"x")
    stub = tmp_path / "python"
    record = tmp_path / "calls"
    stub.write_text(f'#!/usr/bin/env bash\necho "$PWD $*" >> {record}\n')
    stub.chmod(0o755)
    env = os.environ | {"PYTHON": str(stub), "DSTEPS": "7", "GUIDANCE": "2.5"}
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    got = _run("distil", str(tmp_path / "students"), str(teachers), head, env=env)
    assert got.returncode == 0, got.stderr
    calls = []
    for _ in range(100):
        calls = sorted(c for c in (record.read_text().splitlines() if record.exists() else []) if "train-prior" in c)
        if len(calls) == 2:
            break
        time.sleep(0.1)
    assert len(calls) == 2
    assert "runs/world64_data.py" in record.read_text().splitlines()[0]  # the data first (cached)
    for call, run in zip(calls, ("front", "uniform")):
        words = call.split()
        assert words[0] == str(tmp_path / "students")  # run from the clone
        assert words[words.index("--teacher") + 1] == str(
            teachers / "runs" / f"prior-world64p4-{run}" / "model.safetensors"
        )
        assert words[words.index("--teacher-guidance") + 1] == "2.5" and words[words.index("--steps") + 1] == "7"
        assert words[words.index("--out") + 1] == f"runs/prior-world64p4-{run}-1call"
    clone_head = subprocess.run(["git", "-C", str(tmp_path / "students"), "rev-parse", "HEAD"], capture_output=True,
                                text=True).stdout.strip()  # fmt: skip
    assert clone_head == head
    got = _run("distil", str(tmp_path / "students"), str(teachers), "HEAD~1", env=env)
    assert got.returncode == 2 and "its runs belong to that commit" in got.stdout
