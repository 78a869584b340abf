"""Transfer server node: on request, transfer the source model to the bags recorded since the last transfer.

Wiring (defaults; every name is a :class:`TransferServerParams` field):

* ``/t42/transfer`` (std_srvs/srv/Trigger): runs one transfer
  (:func:`t42_transfer.transfer.online.run_transfer`: new bags, held-out
  scoring, atomic saves, state file) and answers ``success=True`` with a one-line
  summary (method, data used, held-out divergence time and MSE, model path), or
  ``success=False`` with the reason (no new bags, too little data, an unreadable
  bag, an unusable source model; nothing is written then), or ``busy`` while a
  transfer runs;
* ``/diagnostics`` (diagnostic_msgs/msg/DiagnosticArray): one status named
  :data:`STATUS_NAME`, level OK while running and when done, WARN when a request
  was refused, ERROR when the transfer failed; key-values ``stage`` (loading,
  training, evaluating, saving, done, failed), ``elapsed_s``, ``method``,
  ``bags`` and what is known so far; while training, the last finished epoch:
  ``phase`` (what the method trains, e.g. ``residual``), ``epoch`` (0 before the
  first), ``epochs`` (the phase's budget; early stopping may end it sooner),
  ``train_loss`` and, when the method validates, ``val_loss``.  Published at
  every stage change, every epoch and every ``progress_period_s`` while running;
* ``/t42/model_updated`` (std_msgs/msg/String, latched): the path of each new
  ``transferred_<NNN>.safetensors`` (a file never rewritten, so a planner can load
  it while the next transfer replaces ``current.safetensors``); on start the node
  republishes the last one recorded in the state file.

Blocking design.  Trigger is request/response and the answer is the summary, so
the handler returns only when the transfer is done.  It runs the transfer in a
worker thread and meanwhile publishes the progress itself (a timed wait on the
worker, no transport timer), so diagnostics flow even when the backend runs the
handler inside the node's spin loop.  A call arriving while one runs takes a
non-blocking lock and, failing, answers ``busy`` at once.  That needs the backend
to run handlers concurrently, so the service is registered with ``concurrent=True``:
Cyclone and rclpy then run each request in a thread of its own, and the in-process
bus runs each handler in its caller's thread anyway.

No handler raises; failures are logged with ``transport.logger`` and answered.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from msg_adapters import DIAGNOSTIC_ARRAY, DIAGNOSTICS_TOPIC, TYPESTORE, diagnostic_array
from t42_transfer.ros import qos
from t42_transfer.ros.naming import validate_name
from t42_transfer.ros.transport import Transport, service_classes
from t42_transfer.transfer.config import TransferConfig
from t42_transfer.transfer.methods import METHODS
from t42_transfer.transfer.online import (
    OnlineTransferSpec,
    TransferRefused,
    TransferResult,
    config_with_overrides,
    latest_model,
    run_transfer,
)

STRING = "std_msgs/msg/String"
TRIGGER = "std_srvs/srv/Trigger"

TRANSFER_SERVICE = "/t42/transfer"
MODEL_TOPIC = "/t42/model_updated"
STATUS_NAME = "t42_transfer: transfer"
"""Name of the node's status in ``/diagnostics``."""


@dataclass(frozen=True)
class TransferServerParams:
    """Parameters of :class:`TransferServer` (the node's ROS parameters)."""

    source_model: str | Path
    """The source hand's model (a transition model checkpoint); read at every call."""
    model_dir: str | Path
    """Where ``transferred_<NNN>.safetensors``, ``current.safetensors`` and the state file live."""
    bag_dir: str | Path = ""
    """Finished bags here not used by an earlier transfer are the target data (unless ``bags`` is set)."""
    bags: tuple[str, ...] = ()
    """Explicit target bags instead of ``bag_dir``; those used by an earlier transfer are skipped too."""
    method: str = "cumulative_residual"
    """Any name in :data:`t42_transfer.transfer.METHODS`."""
    config: Mapping[str, Any] = field(default_factory=dict)
    """Overrides of :class:`TransferConfig`'s paper defaults, nested: ``{cumulative_residual: {train: {epochs: 50}}}``."""
    holdout_fraction: float = 0.25
    """Share of the new episodes held out (at least one) to score the model."""
    min_episodes: int = 2
    """Fewer new episodes than this are refused as too little data."""
    seed: int = 0
    service: str = TRANSFER_SERVICE
    model_topic: str = MODEL_TOPIC
    diagnostics_topic: str = DIAGNOSTICS_TOPIC
    progress_period_s: float = 0.5
    """Diagnostics are re-published this often while a transfer runs."""

    def __post_init__(self) -> None:
        if not str(self.bag_dir) and not self.bags:
            raise ValueError("set bag_dir or bags: the transfer needs target bags")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {sorted(METHODS)}, got {self.method!r}")
        object.__setattr__(self, "bags", tuple(str(b) for b in self.bags))
        object.__setattr__(self, "config", dict(self.config))
        self.transfer_config()  # ValueError for an unknown key or a wrong type
        if not 0.0 < self.holdout_fraction < 1.0:
            raise ValueError(f"holdout_fraction must be in (0, 1), got {self.holdout_fraction!r}")
        if not isinstance(self.min_episodes, int) or self.min_episodes < 2:
            raise ValueError(f"min_episodes must be an int >= 2 (one to train on, one held out), got {self.min_episodes!r}")
        if not self.progress_period_s > 0:
            raise ValueError(f"progress_period_s must be positive, got {self.progress_period_s!r}")
        validate_name(self.service, "service")
        validate_name(self.model_topic)
        validate_name(self.diagnostics_topic)

    def transfer_config(self) -> TransferConfig:
        return config_with_overrides(self.config)

    def spec(self) -> OnlineTransferSpec:
        """What one call runs on (built per call, so the files are looked at afresh)."""
        return OnlineTransferSpec(
            source_model=Path(self.source_model), model_dir=Path(self.model_dir),
            bag_dir=Path(self.bag_dir) if str(self.bag_dir) else None, bags=tuple(Path(b) for b in self.bags),
            method=self.method, config=self.transfer_config(), holdout_fraction=self.holdout_fraction,
            min_episodes=self.min_episodes, seed=self.seed,
        )


class TransferServer:
    """Serves transfers; see the module docstring for behaviour."""

    def __init__(self, transport: Transport, params: TransferServerParams) -> None:
        self.transport = transport
        self.params = params
        self.log = transport.logger
        self.last_result: TransferResult | None = None
        self._job = threading.Lock()
        """Held while a transfer runs: a second call that cannot take it is answered busy."""
        self._publishing = threading.Lock()
        """Worker and handler threads publish the status one at a time."""
        self._status: dict[str, Any] = {"stage": "idle", "level": "OK", "message": "idle", "values": {}}
        self._started = time.monotonic()
        _, self._Response = service_classes(TRIGGER)
        self._String = TYPESTORE.types[STRING]
        self._diagnostics = transport.publisher(params.diagnostics_topic, DIAGNOSTIC_ARRAY, qos.DEFAULT)
        self._updates = transport.publisher(params.model_topic, STRING, qos.TRANSIENT_LOCAL)
        transport.service(params.service, TRIGGER, self._on_transfer, concurrent=True)
        latest = latest_model(Path(params.model_dir))
        if latest is not None:
            self._updates.publish(self._String(data=str(latest)))

    @property
    def busy(self) -> bool:
        return self._job.locked()

    def close(self) -> None:
        """Nothing to release; a running transfer finishes in its (daemon) thread, its saves are atomic."""
        if self.busy:
            self.log.warning("closing while a transfer runs; it finishes in the background, unpublished")

    # ------------------------------------------------------------------ service
    def _on_transfer(self, request: Any) -> Any:
        if not self._job.acquire(blocking=False):
            status = self._status
            return self._Response(
                success=False,
                message=f"busy: a {self.params.method} transfer is {status['stage']} "
                        f"({time.monotonic() - self._started:.0f} s in); call again when it is done",
            )
        try:
            ok, message = self._run()
        except Exception as err:  # a service handler must answer, not raise
            self.log.exception("transfer service failed")
            ok, message = False, f"failed: {type(err).__name__}: {err}"
        finally:
            self._job.release()
        return self._Response(success=ok, message=message)

    def _run(self) -> tuple[bool, str]:
        """Run one transfer in a worker thread, publishing progress until it ends; (success, message)."""
        self._started = time.monotonic()
        self._status = {"stage": "loading", "level": "OK", "message": "starting", "values": {}}
        outcome: dict[str, Any] = {}
        done = threading.Event()
        spec = self.params.spec()

        def work() -> None:
            try:
                outcome["result"] = run_transfer(spec, self._report)
            except TransferRefused as err:
                outcome["refused"] = str(err)
            except Exception as err:  # reported, never raised from the thread
                self.log.exception("transfer failed")
                outcome["error"] = f"failed: {type(err).__name__}: {err}"
            finally:
                done.set()

        threading.Thread(target=work, name="transfer", daemon=True).start()
        while not done.wait(self.params.progress_period_s):
            self._publish_status()
        result: TransferResult | None = outcome.get("result")
        if result is None:
            refused = "refused" in outcome
            reason = outcome["refused"] if refused else outcome["error"]
            (self.log.warning if refused else self.log.error)("transfer not done: %s", reason)
            self._set_status("failed", "WARN" if refused else "ERROR", reason, {})
            return False, reason
        self.last_result = result
        summary = result.summary()
        self.log.info("transfer done: %s", summary)
        try:
            self._updates.publish(self._String(data=str(result.model_path)))
        except Exception:  # e.g. the node closed meanwhile: the model is saved all the same
            self.log.exception("could not announce %s on %s", result.model_path, self.params.model_topic)
        self._set_status("done", "OK", summary, {
            "divergence_steps": result.divergence_steps, "position_mse_mm2": result.position_mse_mm2,
            "model": str(result.model_path),
        })
        return True, summary

    # ------------------------------------------------------------------ diagnostics
    _MESSAGES = {
        "loading": "loading the source model and the new bags",
        "training": "training",
        "evaluating": "scoring on held-out target episodes",
        "saving": "saving the model",
    }

    def _report(self, stage: str, info: Mapping[str, object]) -> None:
        """Progress callback of :func:`run_transfer` (worker thread); an epoch report says which in the message."""
        message = self._MESSAGES.get(stage, stage)
        if stage == "training" and "phase" in info:
            message = f"training {info['phase']}: epoch {info['epoch']}/{info['epochs']}"
        self._set_status(stage, "OK", message, info)

    def _set_status(self, stage: str, level: str, message: str, info: Mapping[str, object]) -> None:
        values = {**self._status["values"], **info}
        self._status = {"stage": stage, "level": level, "message": message, "values": values}
        self._publish_status()

    def _publish_status(self) -> None:
        """Publish the current status; failures are logged (it runs from worker and handler threads).

        The status is read under the lock, so a periodic publish cannot send an
        older epoch after the worker has published a newer one.
        """
        try:
            with self._publishing:
                if self.transport.closed:
                    return
                status = self._status
                values = {
                    "stage": status["stage"], "elapsed_s": f"{time.monotonic() - self._started:.1f}",
                    "method": self.params.method, **status["values"],
                }
                self._diagnostics.publish(diagnostic_array(
                    STATUS_NAME, status["level"], status["message"], values, self.transport.now_ns(),
                ))
        except Exception:
            self.log.exception("could not publish the transfer status")
