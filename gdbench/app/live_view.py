"""``gdbench generate --view``: the scene served in the browser viewer while it trains
(docs/viewer.md, "Watching a run train").

``LiveView`` is the trainer's ``on_step`` callback. On the first step it starts the viewer
(``viewer.serve``, not blocking) with the scene as it is; every ``every`` steps it copies the
parameters (a few hundred kilobytes: the only work on the training thread) and hands the copy to
a worker thread, which builds viser's splat arrays and sends them (``Viewer.update_scene``). A
copy that arrives while the worker is busy replaces the one waiting, so a slow browser never
holds the run back. What the step pays was measured by ``scripts/bench_live_view.py``.
"""

from __future__ import annotations

import queue
import threading

from gdbench.core.scene import GaussianScene


class LiveView:
    def __init__(self, *, every: int = 100, host: str = "127.0.0.1", port: int = 8080, verbose: bool = True):
        if isinstance(every, bool) or not isinstance(every, int) or every < 1:
            raise ValueError(f"view_every (--view-every): expected an int >= 1 (steps), got {every!r}")
        self.every, self.host, self.port, self.verbose = every, host, port, verbose
        self.viewer = None
        self.updates = 0
        """Scenes the worker has sent to the viewer."""
        self._box: queue.Queue = queue.Queue(maxsize=1)
        self._worker: threading.Thread | None = None

    def __call__(self, state) -> None:
        if self.viewer is None:
            from gdbench.app.viewer import serve

            self.viewer = serve(_snapshot(state), host=self.host, port=self.port, block=False, verbose=False)
            if self.verbose:
                print(f"gdbench generate: watching the run at {self.viewer.url} (every {self.every} steps)", flush=True)
            self._worker = threading.Thread(target=self._send, name="gdbench-live-view", daemon=True)
            self._worker.start()
            return
        if state.step % self.every == 0:
            snap = _snapshot(state)
            try:
                self._box.get_nowait()  # drop the copy still waiting: the newer one replaces it
            except queue.Empty:
                pass
            self._box.put_nowait(snap)

    def _send(self) -> None:
        while True:
            scene = self._box.get()
            if scene is None:
                return
            self.viewer.update_scene(scene)
            self.updates += 1

    def close(self) -> None:
        """Stop the worker, once it has sent the last scene handed to it, and the server."""
        if self._worker is not None:
            try:
                self._box.put(None, timeout=30)  # waits for the worker to take the copy still waiting
            except queue.Full:  # a worker stuck in a send: the server's stop ends it
                pass
            self._worker.join(timeout=30)
        if self.viewer is not None:
            self.viewer.stop()


def _snapshot(state) -> GaussianScene:
    """The state's scene, detached and copied to the CPU (the trainer goes on changing its own)."""
    return state.scene().detach().to("cpu").clone()
