"""Transfer server node: on request, transfer the source model to the bags recorded since the last transfer.

Wiring (relative names: remap them with ``--ros-args -r``, or run under a namespace):

* ``t42/transfer`` (t42_interfaces/action/Transfer): the action. A goal names the method (``""``: the ``method``
  parameter) and the bags (none: the bags closed since the last transfer, as the service takes them; given paths:
  exactly those, used before or not; relative ones from the server's working directory). Every goal is accepted and
  then ends with a result whose ``message`` says why (a rejection could not say): SUCCEEDED with the model path, the
  held-out divergence and MSE of the model, the source and the hold-still baseline, ``auto``'s candidates and their
  held-out divergence, and the bags skipped as unreadable (or missing) with why; ABORTED with the reason for an
  unknown method (``unknown transfer method ...``, at once), a goal while a transfer runs (``busy: ...``, at once),
  the node stopping (:data:`SHUTTING_DOWN`; a goal accepted but not started yet: ``the node is shutting down; ...``;
  sent before the node leaves) and every refusal or failure the service answers; CANCELED when the client cancelled
  it: training stops after the epoch in progress and nothing is written (the current model, the numbered models,
  the state file stay as they were, nothing is announced). A cancel is refused once the save has begun. Feedback at
  each stage change and after every training epoch: ``phase`` (the stage; ``training: <what it trains>`` once an
  epoch named it), epoch / epochs, train and validation loss;
* ``t42/transfer_now`` (std_srvs/srv/Trigger; named ``t42/transfer`` until the action took that name): the same
  transfer for callers without the action type: the method parameter, the bags closed since the last transfer
  (:func:`t42_transfer.transfer.online.run_transfer`: new bags, held-out scoring, atomic saves, state file) and
  answers ``success=True`` with a one-line summary (method, data used, held-out divergence time and MSE, model path,
  and each new bag it skipped as unreadable, with why: the others are used), or ``success=False`` with a one-line
  reason (no new bags, too little data in the readable ones, naming the skipped bags; an unusable source model or
  ``config`` file; nothing is written then), or ``busy: ...`` at once while a transfer (a call, a goal, an automatic
  one) runs;
* ``diagnostics`` (diagnostic_msgs/msg/DiagnosticArray): one status named
  :data:`~t42_transfer.nodes.transfer_status.STATUS_NAME`, level OK while running and when done, WARN when a request
  was refused, ERROR when the transfer failed; key-values ``stage`` (loading,
  training, evaluating, saving, done, failed, cancelled), ``elapsed_s``, ``method``,
  ``bags`` and what is known so far; while training, the last finished epoch:
  ``phase`` (what the method trains, e.g. ``residual``), ``epoch`` (0 before the
  first), ``epochs`` (the phase's budget; early stopping may end it sooner),
  ``train_loss`` and, when the method validates, ``val_loss``; when done with
  method ``auto``, ``picked_method`` and one ``candidate.<method>`` per candidate
  (its held-out score, or why it failed).  Published at
  every stage change, every epoch and every ``progress_period_s`` while running, and
  every second after a transfer ended, so a monitor started later hears how the last one ended;
* ``t42/model_updated`` (t42_interfaces/msg/ModelUpdated, latched): each new
  ``transferred_<NNN>.safetensors`` (its absolute path: a file never rewritten, so a planner can load
  it while the next transfer replaces ``current.safetensors``), when it was saved, the method that made it and
  the episodes it trained on; on start the node republishes the last one recorded in the state file;
* ``recorder/bag_closed`` (t42_interfaces/msg/BagClosed, read VOLATILE: only bags closed while the server runs):
  with ``auto_transfer_after_bags`` N > 0, every N-th new closed bag holding an episode (as the recorder's
  ``read_bag`` counted) starts a transfer by itself, exactly as a ``t42/transfer_now`` call (the same code: the
  bags since the last transfer, diagnostics, the model announced); if a transfer is running then, it runs once
  more after it (triggers while it waits count as one).  0 (the default) leaves the server to its callers.

Concurrency.  Trigger is request/response and the answer is the summary, so the
service callback returns only when the transfer is done; an action goal's execute callback likewise returns with
its result (the goal is EXECUTING meanwhile).  Both are in a
:class:`~rclpy.callback_groups.ReentrantCallbackGroup`, so on a
``MultiThreadedExecutor`` (``t42 node`` spins one for this node: ``executor_threads``) a second request or goal
runs in another executor thread while the first trains: it fails to take a non-blocking
lock and answers ``busy`` at once; cancel requests are served meanwhile.  The first callback runs the transfer in a
worker thread and, while waiting for it, publishes the progress itself every
``progress_period_s``, so diagnostics flow without needing a free executor
thread.  Parameters other than the model and bag locations take effect with the
next call.  The science (torch) is not imported with this module: checking the parameters (the method
registry, the ``config`` file) imports it when the node is made.

No callback raises; failures are logged with the node's logger and answered.
"""

from __future__ import annotations

import calendar
import dataclasses
import math
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rclpy.action import CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.node import Node
from std_srvs.srv import Trigger
from t42_interfaces.msg import BagClosed, ModelUpdated

from msg_adapters import names
from msg_adapters.diagnostics import PERIOD_S as DIAGNOSTICS_PERIOD_S
from msg_adapters.events import SNAPSHOT, bag_closed_event
from msg_adapters.transfer import (
    Scores,
    TransferOutcome,
    model_updated_msg,
    skipped_pairs,
    transfer_feedback,
    transfer_request,
    transfer_result,
    transfer_type,
)
from t42_transfer.nodes.transfer_server_params import TransferServerParams, method_names
from t42_transfer.nodes.transfer_status import TransferStatus
from t42_transfer.ros.dirs import claim_made
from t42_transfer.ros.goals import AnsweringActionServer
from t42_transfer.ros.node_lifetime import destroyed_if_init_fails
from t42_transfer.ros.params import LiveParams
from t42_transfer.ros.qos import profile

if TYPE_CHECKING:  # the science is imported on first use (node start-up time)
    from t42_transfer.transfer.online import TransferResult

CLOSE_WAIT_S = 10.0
"""How long closing the node waits for a cancelled transfer to stop (it stops at its next epoch, or finishes a
save under way) before leaving it to end with the process."""
RESULT_ASK_WAIT_S = 2.0
"""How long closing the node waits for the client of a goal that ended to ask for its result (see :meth:`close`)."""
SHUTTING_DOWN = "the node is shutting down; the transfer is cancelled, the previous model stays"
"""The message of a goal's (or call's) result when closing the node cancelled its transfer."""
FEEDBACK_LEAD_S = 0.2
"""Wall time between a goal's last feedback and its result (see ``_on_goal``): a transfer takes seconds."""


def one_line(text: str) -> str:
    """``text`` with its line breaks (and runs of blanks) made single spaces: a service answer is one line."""
    return " ".join(text.split())


@dataclass
class Job:
    """One transfer as asked for: by a call, a goal or the automatic trigger."""

    method: str
    """The method to run (the parameter's when the caller named none)."""
    bags: tuple[str, ...] = ()
    """Exactly these bags; empty: the bags closed since the last transfer."""
    feedback: Callable[[str, Mapping[str, object]], None] | None = None
    """Also told each progress report (a goal's feedback); its failures are logged, never raised."""
    handle: Any = None
    """The action goal it runs for, if any."""
    cancel: threading.Event = field(default_factory=threading.Event)
    """Set to stop it (a goal cancelled): checked after each training epoch and stage, until the save begins."""
    cancelled: bool = False
    """It stopped on :attr:`cancel`: nothing was written."""


def answering(callback: Callable[..., Any]) -> Callable[..., Any]:
    """A call callback that closing the node waits for (see :meth:`TransferServer.close`) until it returned (a goal
    is waited for from its acceptance until its result went out: :class:`AnsweringActionServer`)."""

    def counted(self: TransferServer, *args: Any) -> Any:
        with self._in_flight_lock:
            self._in_flight += 1
        try:
            return callback(self, *args)
        finally:
            with self._in_flight_lock:
                self._in_flight -= 1

    counted.__name__, counted.__doc__ = callback.__name__, callback.__doc__
    return counted


class TransferServer(Node):
    """Serves transfers; see the module docstring for behaviour."""

    params_class = TransferServerParams  # the one its LiveParams declares; t42 node NAME --help lists it

    executor_threads = 4
    """A MultiThreadedExecutor (``t42 node`` reads this): a second call is answered while one trains."""

    @destroyed_if_init_fails
    def __init__(self, **node_kwargs: Any) -> None:
        super().__init__("transfer_server", **node_kwargs)
        self._params = LiveParams(self, self.params_class, self._on_params)
        self.log = self.get_logger()
        self.last_result: TransferResult | None = None
        self._job = threading.Lock()
        """Held while a transfer runs: a second call that cannot take it is answered busy."""
        self._running: Job | None = None
        """The job holding :attr:`_job`."""
        self._worker: threading.Thread | None = None
        """The thread of the newest transfer (closing the node waits for it)."""
        self._auto_thread: threading.Thread | None = None
        self._status = TransferStatus(self, self.params.method)
        self._closed = False
        self._in_flight = 0
        """Call callbacks running (closing waits for their answers; for goals, see :meth:`_answered`)."""
        self._in_flight_lock = threading.Lock()
        self.create_timer(DIAGNOSTICS_PERIOD_S, lambda: self._status.publish_ended(self.busy))
        self._updates = self.create_publisher(ModelUpdated, names.MODEL_UPDATED,
                                              profile(names.OFFERED[names.MODEL_UPDATED]))
        group = ReentrantCallbackGroup()
        self.create_service(Trigger, names.TRANSFER_NOW, self._on_transfer, qos_profile=profile(names.REQUESTS),
                            callback_group=group)
        self._action = AnsweringActionServer(
            self, transfer_type(), names.TRANSFER, execute_callback=self._on_goal,
            goal_callback=lambda request: GoalResponse.ACCEPT, cancel_callback=self._on_cancel,
            callback_group=group,
            # a burst of callers each gets an answer (rclpy's default depth of 10 loses requests, as for services)
            goal_service_qos_profile=profile(names.REQUESTS), cancel_service_qos_profile=profile(names.REQUESTS),
            result_service_qos_profile=profile(names.REQUESTS),
        )
        import torch

        from t42_transfer.models.training import import_optimizer_machinery

        torch.set_num_threads(self.params.torch_threads)
        # In a thread of its own while the server waits for its first goal, not inside its first transfer.
        threading.Thread(target=import_optimizer_machinery, name="import-torch-optim", daemon=True).start()
        # the directories as each call takes them (claimed there too): a shared one fails at start, in one line
        self._announce_latest(self.params.spec(self.get_namespace()).model_dir)
        if not self.params.source_model.is_file():  # said now, not first at the transfer a user waits for
            where = self.params.source_model.absolute()  # (the node's working directory may not be the user's)
            self.log.warning(f"source_model {where} does not exist (yet) or is no file: every transfer fails until "
                             f"it is there; make it from the source hand's bags with t42 model train BAGS --out "
                             f"{where} (t42 demo makes one for the simulated hands)")
        self.new_bags = 0
        """New closed bags (holding an episode) counted towards the next automatic transfer."""
        self.auto_results: list[tuple[bool, str]] = []
        """(success, message) of each automatic transfer, as a call would have been answered."""
        self._auto_due = threading.Event()
        self.create_subscription(BagClosed, names.BAG_CLOSED, self._on_bag_closed, profile(names.EVENT_READER))
        self._auto_thread = threading.Thread(target=self._auto_transfers, name="auto_transfer", daemon=True)
        self._auto_thread.start()

    @property
    def params(self) -> TransferServerParams:
        return self._params.value

    @property
    def busy(self) -> bool:
        return self._job.locked()

    def close(self) -> None:
        """Stop publishing and cancel a running transfer (the previous model stays), waiting for its thread to end:
        a transfer left running would be cut off by the process's exit wherever it was.  A goal or call in progress,
        or a goal accepted whose execution has not started, then ends (ABORTED: the node is shutting down) and its
        answer goes out before this returns, to a client that asks for it up to :data:`RESULT_ASK_WAIT_S` after its
        end: the node's executor is spun meanwhile (from the thread that spins it), as the action server sends it.
        Called again (``destroy_node`` does), it answers the goals accepted since (a closed node still takes goals)."""
        threads: list[threading.Thread] = []
        if not self._closed:
            self._closed = self._status.closed = True
            job = self._running
            if job is not None:
                job.cancel.set()
                self.log.warning("closing while a transfer runs: it is cancelled at its next epoch (the previous "
                                 "model stays; a save under way completes)")
            threads = [t for t in (self._worker, self._auto_thread) if t not in (None, threading.current_thread())]
        elif self._answered():
            return
        deadline = time.monotonic() + CLOSE_WAIT_S
        self._spin_until(lambda: not any(t.is_alive() for t in threads) and self._answered(), deadline)
        for thread in threads:
            if thread.is_alive():
                self.log.warning(f"the {thread.name} thread still runs after {CLOSE_WAIT_S:g} s; it ends with the "
                                 "process, unannounced (saves are atomic)")
        if not self._answered():
            self.log.warning(f"a {names.TRANSFER} goal or {names.TRANSFER_NOW} call is still unanswered after "
                             f"{CLOSE_WAIT_S:g} s")

    def _answered(self) -> bool:
        """No call callback runs, nor does an accepted goal (started or not) owe a client its result yet."""
        with self._in_flight_lock:
            calls = self._in_flight
        return calls == 0 and self._action.unanswered(RESULT_ASK_WAIT_S) == 0

    def _spin_until(self, condition: Callable[[], bool], deadline: float) -> None:
        """Wait until ``condition`` or ``deadline``, spinning the node's executor when it is this thread's to spin
        (the main thread, where ``t42 node`` and the tests spin it): a result request still in the middleware is
        then taken and answered too."""
        executor = self.executor if threading.current_thread() is threading.main_thread() else None
        while not condition() and time.monotonic() < deadline:
            if executor is None:
                time.sleep(0.02)
                continue
            try:
                executor.spin_once(timeout_sec=0.02)
            except Exception as err:  # shut down, or spun elsewhere after all: wait without it
                self.log.debug(f"not spinning while closing: {err!r}")
                executor = None

    def destroy_node(self) -> None:
        self.close()
        self._action.destroy()
        super().destroy_node()

    def _announce_latest(self, model_dir: Path) -> None:
        """Republish the model the state file names last (latched: for planners that start later)."""
        from t42_transfer.transfer.online import latest_transfer

        latest = latest_transfer(model_dir)
        if latest is None:
            return
        path, record = latest
        try:
            stamp_ns = max(0, calendar.timegm(time.strptime(str(record.get("time_utc")), "%Y-%m-%dT%H:%M:%SZ")))
            stamp_ns *= 10**9
        except (TypeError, ValueError, OverflowError):
            stamp_ns = 0
        method = record.get("made_by") or record.get("method") or ""
        episodes = record.get("train_episodes")
        try:
            self._updates.publish(model_updated_msg(stamp_ns, str(path.absolute()), str(method),
                                                    episodes if isinstance(episodes, int) else 0))
        except ValueError as err:  # a hand-edited state file: announce the path alone
            self.log.warning(f"state file record of {path} unusable ({err}); announcing the path alone")
            self._updates.publish(model_updated_msg(0, str(path.absolute()), "", 0))

    # ------------------------------------------------------------------ callbacks
    def _on_params(self, old: TransferServerParams, new: TransferServerParams) -> None:
        changed = [f"{f.name} {getattr(old, f.name)} -> {getattr(new, f.name)}" for f in dataclasses.fields(new)
                   if getattr(old, f.name) != getattr(new, f.name)]
        self.log.info(f"{', '.join(changed)}: takes effect with the next call")

    @answering
    def _on_transfer(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if self._closed:
            response.success, response.message = False, "the node is shutting down; call again when it runs"
            return response
        if not self._job.acquire(blocking=False):
            response.success, response.message = False, self._status.busy("call again")
            return response
        try:
            outcome = self._run(Job(self.params.method))
            ok, message = outcome.success, outcome.message
        except Exception as err:  # a service callback must answer, not raise
            self.log.error(f"transfer service failed: {err!r}")
            ok, message = False, f"failed: {type(err).__name__}: {err}"
        finally:
            self._job.release()
        response.success, response.message = ok, one_line(message)
        return response

    # ------------------------------------------------------------------ the action
    def _on_goal(self, handle: Any) -> Any:
        """Execute callback of ``t42/transfer``: runs the goal's transfer here (an executor thread) and returns
        its result; ends the goal SUCCEEDED, ABORTED (with the reason) or CANCELED."""
        try:
            if self._closed:
                return self._end(handle, TransferOutcome(False, "the node is shutting down; send it when it runs"))
            request = transfer_request(handle.request)
            method = request.method or self.params.method
            if method not in method_names():
                return self._end(handle, TransferOutcome(False, f"unknown transfer method {method!r}; expected one "
                                                                f"of {method_names()} (or '' for the server's)"))
            if request.problem:
                return self._end(handle, TransferOutcome(False, request.problem))
            if handle.is_cancel_requested:
                return self._end(handle, TransferOutcome(False, "cancelled before it started; nothing was written"),
                                 cancelled=True)
            if not self._job.acquire(blocking=False):
                return self._end(handle, TransferOutcome(False, self._status.busy("send the goal again")))
            fed = [0.0]  # when the last feedback went out (monotonic s)

            def feed(stage: str, info: dict) -> None:
                handle.publish_feedback(transfer_feedback(stage, info))
                fed[0] = time.monotonic()

            job = Job(method, request.bags, feed, handle)
            try:
                outcome = self._run(job)
            finally:
                self._job.release()
            # rclpy 7.1.6's ActionClient drops the feedback it takes after the result: the last stages' feedback
            # gets a head start on the result (seen: 'evaluating' and 'saving' lost, 1 run in 10).
            time.sleep(max(0.0, fed[0] + FEEDBACK_LEAD_S - time.monotonic()))
            return self._end(handle, outcome, job.cancelled)
        except Exception as err:  # an execute callback must end its goal, not raise
            self.log.error(f"transfer goal failed: {err!r}")
            return self._end(handle, TransferOutcome(False, f"failed: {type(err).__name__}: {err}"))

    def _end(self, handle: Any, outcome: TransferOutcome, cancelled: bool = False) -> Any:
        """Set the goal's final state; its result."""
        try:
            if outcome.success:
                handle.succeed()
            elif cancelled:
                deadline = time.monotonic() + 2.0  # the server marks the goal CANCELING once our callback returned
                while not handle.is_cancel_requested and not self._closed and time.monotonic() < deadline:
                    time.sleep(0.01)
                handle.canceled() if handle.is_cancel_requested else handle.abort()
            else:
                handle.abort()
        except Exception as err:  # the node is being destroyed, or the state moved on: the result still goes out
            self.log.warning(f"could not end a {names.TRANSFER} goal: {err!r}")
        return transfer_result(dataclasses.replace(outcome, message=one_line(outcome.message)))

    def _on_cancel(self, handle: Any) -> CancelResponse:
        """Accept cancelling a goal until its save begins: the running one stops after its epoch in progress."""
        job = self._running
        if job is not None and job.handle is not None and job.handle.goal_id == handle.goal_id:
            if self._status.stage in ("saving", "done"):
                return CancelResponse.REJECT
            job.cancel.set()
        return CancelResponse.ACCEPT

    # ------------------------------------------------------------------ automatic transfers
    def _on_bag_closed(self, msg: BagClosed) -> None:
        try:
            every = self.params.auto_transfer_after_bags
            event = bag_closed_event(msg)
            if every <= 0 or event.episodes == 0 or event.reason == SNAPSHOT:  # a snapshot repeats recorded steps
                return
            self.new_bags += 1
            self.log.info(f"{event.path} closed ({event.reason}, {event.episodes} episodes): "
                          f"{self.new_bags}/{every} new bags")
            if self.new_bags >= every:
                self.new_bags = 0
                self._auto_due.set()
        except Exception as err:  # never raise from a callback
            self.log.error(f"could not handle a message on {names.BAG_CLOSED}: {err!r}")

    def _auto_transfers(self) -> None:
        """The automatic transfers' thread: each due one takes the job lock as a call does, waiting for a
        running transfer to end (then it runs once more)."""
        while not self._closed:
            if not self._auto_due.wait(0.2):
                continue
            while not self._job.acquire(timeout=0.2):
                if self._closed:
                    return
            self._auto_due.clear()  # after the wait: the triggers while a transfer ran make one run
            try:
                if self._closed:
                    return
                self.log.info(f"automatic transfer after {self.params.auto_transfer_after_bags} new bags")
                outcome = self._run(Job(self.params.method))
                self.auto_results.append((outcome.success, one_line(outcome.message)))
            except Exception as err:  # logged, never raised from the thread
                self.log.error(f"automatic transfer failed: {err!r}")
                self.auto_results.append((False, f"failed: {type(err).__name__}: {err}"))
            finally:
                self._job.release()

    # ------------------------------------------------------------------ one transfer
    def _run(self, job: Job) -> TransferOutcome:
        """Run ``job`` in a worker thread (the job lock held), publishing progress until it ends."""
        from t42_transfer.transfer.online import TransferCancelled, TransferRefused, run_transfer

        params = self.params
        self._status.begin(job.method)
        self._running = job
        try:
            spec = dataclasses.replace(params.spec(self.get_namespace()), method=job.method)
            if job.bags:
                spec = dataclasses.replace(spec, bags=tuple(Path(b) for b in job.bags), exact_bags=True)
        except ValueError as err:  # the config file changed since it was set
            return self._not_done(str(err), refused=True)
        outcome: dict[str, Any] = {}
        done = threading.Event()

        def report(stage: str, info: Mapping[str, object]) -> None:
            self._status.report(stage, info)
            if job.feedback is not None:
                try:
                    job.feedback(stage, info)
                except Exception as err:  # a goal handle gone with the node: the transfer goes on
                    self.log.warning(f"could not publish {names.TRANSFER} feedback: {err!r}")

        def work() -> None:
            try:
                outcome["result"] = run_transfer(spec, report, cancel=job.cancel.is_set)
            except TransferRefused as err:
                outcome["refused"] = err
            except TransferCancelled as err:
                outcome["cancelled"] = str(err)
            except Exception as err:  # reported, never raised from the thread
                outcome["error"] = f"failed: {type(err).__name__}: {err}"
            finally:  # a save makes model_dir, and may be followed by a failure (writing the state file)
                claim_made(spec.model_dir, self.get_namespace(), params.share_dirs)
                done.set()

        self._worker = threading.Thread(target=work, name="transfer", daemon=True)
        self._worker.start()
        try:
            while not done.wait(params.progress_period_s) and not self._closed:
                if job.handle is not None and job.handle.is_cancel_requested:
                    job.cancel.set()
                self._status.publish()
        finally:
            self._running = None
        return self._conclude(job, outcome, done.is_set())

    def _conclude(self, job: Job, outcome: dict[str, Any], done: bool) -> TransferOutcome:
        """A transfer's answer from what its worker left in ``outcome``: announce and report a new model, or say
        why there is none."""
        result: TransferResult | None = outcome.get("result")
        if result is None:
            if not done or self._closed:  # cancelled by close(): the caller is told why
                if "cancelled" in outcome:
                    self.log.info(f"transfer not done: {one_line(outcome['cancelled'])}")
                return TransferOutcome(False, SHUTTING_DOWN)
            if "cancelled" in outcome:
                job.cancelled = True
                message = one_line(outcome["cancelled"])
                self.log.info(f"transfer not done: {message}")
                self._status.set("cancelled", "OK", message, {})
                return TransferOutcome(False, message)
            if "refused" in outcome:
                refused = outcome["refused"]
                done_outcome = self._not_done(str(refused), refused=True)
                return dataclasses.replace(done_outcome, skipped=skipped_pairs(refused.skipped))
            return self._not_done(outcome["error"], refused=False)
        self.last_result = result
        summary = result.summary()
        if result.skipped:
            self.log.warning(f"skipped {len(result.skipped)} unreadable bag(s): {'; '.join(result.skipped)}")
        self.log.info(f"transfer done: {summary}")
        made_by = result.method if result.selection is None else result.selection.best
        if not self._closed:  # stamped with the save's wall-clock time, as the restart announcement is (UTC)
            self._updates.publish(model_updated_msg(time.time_ns(), str(Path(result.model_path).absolute()), made_by,
                                                    result.episodes))
        picked = {} if result.selection is None else {
            "picked_method": result.selection.best,
            **{f"candidate.{c.method}": c.describe() for c in result.selection.candidates},
        }
        self._status.set("done", "OK", summary, {
            "divergence_steps": result.divergence_steps, "position_mse_mm2": result.position_mse_mm2,
            "model": str(result.model_path), "episodes": result.episodes, "transitions": result.transitions, **picked,
        })
        return outcome_of(result)

    def _not_done(self, reason: str, refused: bool) -> TransferOutcome:
        """Log and publish a refusal (WARN) or a failure (ERROR); the outcome with the one-line reason."""
        reason = one_line(reason)
        (self.log.warning if refused else self.log.error)(f"transfer not done: {reason}")
        self._status.set("failed", "WARN" if refused else "ERROR", reason, {})
        return TransferOutcome(False, reason)


def outcome_of(result: TransferResult) -> TransferOutcome:
    """The action result's content of a successful transfer."""
    candidates = () if result.selection is None else tuple(
        (c.method, math.nan if c.error or c.divergence_steps is None else float(c.divergence_steps))
        for c in result.selection.candidates)
    return TransferOutcome(
        True, result.summary(), str(Path(result.model_path).absolute()),
        Scores(result.divergence_steps, result.position_mse_mm2),
        Scores(result.source_divergence_steps, result.source_position_mse_mm2),
        Scores(result.hold_still_divergence_steps, result.hold_still_position_mse_mm2),
        candidates, skipped_pairs(result.skipped_bags),
    )
