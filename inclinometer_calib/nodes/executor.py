"""The nodes' executor for high-rate subscriptions (:class:`HotPathExecutor`).

A module of its own, importing only rclpy, so that a node that needs nothing of the numerical
core (the recorder) can use it without importing numpy and scipy (``common`` re-exports it).
"""
from __future__ import annotations

import faulthandler
import signal
import sys
import threading
import time
from contextlib import ExitStack

from rclpy.exceptions import InvalidHandle
from rclpy.executors import (ConditionReachedException, Executor, ExternalShutdownException, ShutdownException,
                             TimeoutException)
from rclpy.guard_condition import GuardCondition
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.signals import SignalHandlerGuardCondition, SignalHandlerOptions
from rclpy.subscription import Subscription
from rclpy.task import Task


_RCLPY_HANDLES_SIGINT = (SignalHandlerOptions.ALL, SignalHandlerOptions.SIGINT)


class HotPathExecutor(Executor):
    """A single-threaded executor that gives a node's high-rate subscriptions a wait set of their own.

    rclpy's executors rebuild their wait set from every entity of the node — subscriptions,
    timers, services and parameter services, the QoS event handlers of every publisher and
    subscription: 22 for the correction node — on every wake-up, and take one message per ready
    subscription per wake-up; at 1 kHz that is most of a node's CPU (docs/benchmarks.md, section
    5).  Here the ``hot`` subscriptions (a node's sample streams) are served by a thread of their
    own, on a wait set that holds only them, their QoS event handlers (incompatible QoS or type:
    said as rclpy says them), a stop guard and the SIGINT guard: each wake-up takes every message
    there is, one per subscription in turn (the order in which rclpy's executors deliver them, so
    that streams paired by stamp arrive interleaved, not one stream's backlog before the
    other's), and calls their callbacks (with the message info when the callback takes two
    arguments, as rclpy's executors do).  Every other entity is served as
    :class:`rclpy.executors.SingleThreadedExecutor` serves it, in the thread that spins, from a
    wait set without the hot subscriptions and their event handlers (:meth:`can_execute`).
    The event handlers must go with their subscription: with Fast DDS an event waits on the
    reader's status condition, which every arriving message sets, so left in the other wait set
    they would wake it for every message and find nothing to do (measured: 5 000 empty wake-ups
    in 3 s at 1 kHz, more CPU than before).

    :meth:`add_hot` adds a subscription while the executor runs (the recorder subscribes to the
    topics it discovers): the hot thread builds its wait set again at its next wake-up.

    One lock serialises the callbacks of both threads: the node sees one callback at a time, as
    under a single-threaded executor.  An exception in a hot callback ends the spin with that
    exception, raised in the spinning thread, as rclpy's executors raise a callback's.
    ``wait_timeout_s`` bounds each hot wait, so that the thread also notices a shutdown of the
    context that no guard announced.

    :meth:`shutdown` unregisters the two SIGINT guards (rclpy's and the hot thread's) only once
    no signal can be walking them: rclpy handles SIGINT/SIGTERM in a C++ thread of its own,
    without the GIL or a lock, which triggers every registered SIGINT guard from a global array
    and then shuts the contexts down; unregistering a guard frees that array and destroying it
    frees the guard, so doing either while that thread walks them (right after a Ctrl-C, when
    the node's ``main`` calls :meth:`shutdown`) writes into freed memory — a segfault later,
    anywhere.  After a Ctrl-C in :meth:`spin_once` it waits (at most ``signal_wait_s``) for the
    context to be shut down, that thread's last step; otherwise the guards stay registered
    until the context shuts down (or the executor is collected).  A context that thread shuts
    down just before the spinning thread builds its wait set ends the spin with
    :class:`~rclpy.executors.ExternalShutdownException`, as rclpy's executors end it when that
    happens during the wait (rclpy's wait set would raise ``RCLError``).
    """

    def __init__(self, hot=(), *, context=None, wait_timeout_s: float = 0.5, signal_wait_s: float = 2.0):
        super().__init__(context=context)
        self._interrupted = False   # a KeyboardInterrupt left spin_once: rclpy's signal thread is at work
        self._signal_wait_s = signal_wait_s
        self._sigint_guards = []    # unregistered by _release_sigint_guards, when no signal walks them
        self._hot = []
        self._hot_events = []
        self._hot_ids = set()   # the objects stay referenced (in the lists): their ids stay theirs
        self._hot_changed = False
        self._hot_set_lock = threading.Lock()   # guards the three above (add_hot vs the hot thread)
        self._lock = threading.Lock()
        self._hot_error = None
        self._hot_thread = None
        self._hot_stop = False
        self._hot_timeout_ns = int(wait_timeout_s * 1e9)
        self._hot_gc = GuardCondition(callback=None, callback_group=None, context=self._context)
        self._hot_sigint = SignalHandlerGuardCondition(self._context)
        self._context.on_shutdown(self._wake_hot)
        for sub in hot:
            self.add_hot(sub)

    def add_hot(self, sub) -> None:
        """Serve ``sub`` on the hot path from now on (also while spinning; from any thread or callback)."""
        with self._hot_set_lock:
            if id(sub) in self._hot_ids:
                return
            events = list(sub.event_handlers)
            self._hot.append(sub)
            self._hot_events += events
            self._hot_ids.update(id(entity) for entity in (sub, *events))
            self._hot_changed = True
        self._wake_hot()   # the hot thread takes it into its wait set
        self.wake()        # and the spinning thread's wait set leaves it out

    # ---- the spinning thread: everything but the hot subscriptions ---------------------------
    def can_execute(self, entity) -> bool:
        """False for the hot subscriptions: they stay out of this executor's wait set."""
        return id(entity) not in self._hot_ids and super().can_execute(entity)

    def spin_once(self, timeout_sec=None) -> None:
        self._spin_once(timeout_sec, self._hot_failed)

    def spin_once_until_future_complete(self, future, timeout_sec=None) -> None:
        future.add_done_callback(lambda _: self.wake())
        self._spin_once(timeout_sec, lambda: future.done() or self._hot_failed())

    def _hot_failed(self) -> bool:
        return self._hot_error is not None

    def _spin_once(self, timeout_sec, condition) -> None:
        if self._hot_thread is None and not self._is_shutdown:
            self._hot_thread = threading.Thread(target=self._run_hot, name="hot-path", daemon=True)
            self._hot_thread.start()
        try:
            handler, _, _ = self.wait_for_ready_callbacks(timeout_sec, None, condition)
        except (ShutdownException, TimeoutException, ConditionReachedException):
            pass
        except _rclpy.RCLError:   # rclpy's wait set refuses a context that is down
            if self._context.ok():
                raise
            # rclpy's signal thread shut it down between rclpy's check and its wait set: say so
            # as rclpy says it when that happens during the wait
            raise ExternalShutdownException() from None
        except KeyboardInterrupt:
            self._interrupted = True   # Ctrl-C: shutdown() lets rclpy's signal thread finish first
            raise
        else:
            try:
                with self._lock:
                    handler()
            except KeyboardInterrupt:
                self._interrupted = True
                raise
            if handler.exception() is not None:
                raise handler.exception()
            handler.result()
        if self._hot_error is not None:
            error, self._hot_error = self._hot_error, None
            raise error

    def shutdown(self, timeout_sec=None) -> bool:
        """Stop the hot-path thread (after the callback it may be in), then as rclpy's executors,
        but the SIGINT guards go only when no signal can be walking them (see the class)."""
        self._hot_stop = True
        self._wake_hot()
        thread = self._hot_thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout_sec)
        with self._shutdown_lock:   # the base's: it would destroy rclpy's SIGINT guard now
            self._is_shutdown = True   # first, as the base does: the spinning thread waits no more
            if self._sigint_gc is not None:
                self._sigint_guards += [self._sigint_gc, self._hot_sigint]
                self._sigint_gc = None
        self.wake()
        done = super().shutdown(timeout_sec)
        try:
            self._hot_gc.destroy()   # an ordinary guard: no signal thread knows it
        except InvalidHandle:
            pass
        if ((self._interrupted or INTERRUPTED.is_set())     # (the Ctrl-C raised in a finalizer: the same wait)
                and _rclpy.get_current_signal_handlers_options() in _RCLPY_HANDLES_SIGINT):
            # rclpy's signal thread shuts the context down once it has triggered every SIGINT guard
            end = time.monotonic() + self._signal_wait_s
            while self._context.ok() and time.monotonic() < end:
                time.sleep(0.001)
        self._context.on_shutdown(self._release_sigint_guards)   # now if the context is down already
        return done

    def _release_sigint_guards(self) -> None:
        guards, self._sigint_guards = self._sigint_guards, []
        for gc in guards:
            try:
                gc.destroy()
            except (InvalidHandle, ValueError):   # destroyed already / not registered
                pass

    # ---- the hot-path thread -----------------------------------------------------------------
    def _wake_hot(self) -> None:
        try:
            self._hot_gc.trigger()
        except InvalidHandle:
            pass

    def _run_hot(self) -> None:
        try:
            while not self._hot_stop and self._context.ok():
                with self._hot_set_lock:
                    subs, events = list(self._hot), list(self._hot_events)
                    self._hot_changed = False
                self._serve_hot(subs, events)   # returns when the set changed, or at the end
        except BaseException as exc:  # noqa: B036 — not handled here: re-raised in the spinning thread
            self._hot_error = exc
            self.wake()

    def _serve_hot(self, subs, events) -> None:
        ctx, lock = self._context, self._lock
        guards = (self._hot_gc, self._hot_sigint)
        with ExitStack() as held:   # no handle is destroyed while this thread may use it
            for entity in (*subs, *guards):
                held.enter_context(entity.handle)
            for eh in events:
                held.enter_context(eh)
            held.enter_context(ctx.handle)
            n_events = sum(eh.get_num_entities().num_events for eh in events)
            wait_set = _rclpy.WaitSet(len(subs), len(guards), 0, 0, 0, n_events, ctx.handle)
            handles = [sub.handle for sub in subs]
            guard_handles = [gc.handle for gc in guards]
            with_info = Subscription.CallbackType.WithMessageInfo
            streams = [(sub.handle.take_message, sub.msg_type, sub.raw, sub.callback,
                        sub._callback_type is with_info) for sub in subs]
            while not self._hot_stop and ctx.ok() and not self._hot_changed:
                wait_set.clear_entities()
                for h in handles:
                    wait_set.add_subscription(h)
                for h in guard_handles:
                    wait_set.add_guard_condition(h)
                for eh in events:
                    eh.add_to_wait_set(wait_set)
                wait_set.wait(self._hot_timeout_ns)
                if self._hot_stop or not ctx.ok():
                    break
                for eh in events:   # rare: a publisher with incompatible QoS or type appeared
                    if eh.is_ready(wait_set):
                        task = Task(eh.execute, (eh.take_data(),))
                        with lock:
                            task()
                        task.result()   # raises what the callback raised
                _take_all(streams, lock)

    def take_waiting(self) -> None:
        """Take every message still waiting in the hot subscriptions, after :meth:`shutdown` (a
        node that is stopping: what its DDS reader holds was delivered to it — the recorder writes
        it rather than losing it at its stop)."""
        thread = self._hot_thread
        if thread is not None and thread.is_alive():
            raise RuntimeError("take_waiting: the hot thread still runs (call shutdown first)")
        with self._hot_set_lock:
            subs = list(self._hot)
        with ExitStack() as held:
            live = []
            for sub in subs:
                try:
                    held.enter_context(sub.handle)
                except InvalidHandle:
                    continue
                live.append(sub)
            with_info = Subscription.CallbackType.WithMessageInfo
            _take_all([(sub.handle.take_message, sub.msg_type, sub.raw, sub.callback,
                        sub._callback_type is with_info) for sub in live], self._lock)


def _take_all(streams, lock) -> None:
    """Take and deliver every message waiting: one of each stream per round (the order in which
    rclpy's executors deliver them), until all are empty."""
    ready = streams
    while ready:
        more = []
        with lock:
            for stream in ready:
                take, msg_type, raw, callback, info = stream
                got = take(msg_type, raw)
                if got is not None:
                    if info:
                        callback(*got)
                    else:
                        callback(got[0])
                    more.append(stream)
        ready = more


#: The longest a spinning node waits before it looks again whether its context is still up.
WAKE_S = 0.5


#: Set when a Ctrl-C or SIGTERM landed inside a finalizer, where Python cannot raise it (see
#: :func:`_quiet_interrupted_task`); :func:`spin` then stops as if it had been raised, and
#: :meth:`HotPathExecutor.shutdown` waits for rclpy's signal thread as after a raised one.
INTERRUPTED = threading.Event()

_previous_unraisablehook = sys.__unraisablehook__


def _quiet_interrupted_task(unraisable) -> None:
    """``sys.unraisablehook`` of a node process (:func:`install_stop_hook`): the stop signal's
    marks in rclpy's finalizers, silenced.

    * A Ctrl-C or SIGTERM that lands while rclpy builds a ``Task`` (its executor does, for every
      callback) leaves an object without the fields its ``Future.__del__`` reads, and the garbage
      collector then prints a traceback at exit ("'Task' object has no attribute '_exception'").
    * The ``KeyboardInterrupt`` itself can be raised inside a finalizer (``Task.__del__`` runs
      whenever a callback's task is dropped); Python prints it as an ignored exception and goes
      on.  The node was asked to stop: :data:`INTERRUPTED` is set and :func:`spin` ends.

    Neither says anything about the node, which stopped as asked.  Anything else goes to the
    hook that was in place before."""
    exc, obj = unraisable.exc_value, unraisable.object
    if isinstance(exc, KeyboardInterrupt):
        INTERRUPTED.set()
        return
    if isinstance(exc, AttributeError) and getattr(obj, "__qualname__", "") == "Future.__del__":
        return
    _previous_unraisablehook(unraisable)


#: The signal on which a node prints every thread's Python stack to stderr and goes on
#: (:mod:`faulthandler`, from its own C handler: it is said even when the main thread is blocked
#: inside rclpy or DDS).  The launcher sends it to a node still running 10 s after SIGINT, so the
#: run's log shows where that node hangs (``apps.launcher.Child.stop``).
STACKS_SIGNAL = signal.SIGUSR1


def install_stop_hook() -> None:
    """Make this process a node's: :func:`_quiet_interrupted_task` as ``sys.unraisablehook``,
    :data:`INTERRUPTED` cleared, and :data:`STACKS_SIGNAL` printing every thread's stack.  Called
    by every node's ``main`` (``common.run``, the recorder's), not at import: a process that only
    imports the nodes (a test run, a tool) keeps its own hook and signals."""
    global _previous_unraisablehook
    INTERRUPTED.clear()
    if sys.unraisablehook is not _quiet_interrupted_task:
        _previous_unraisablehook = sys.unraisablehook
        sys.unraisablehook = _quiet_interrupted_task
    faulthandler.register(STACKS_SIGNAL, file=sys.stderr, all_threads=True)


def spin(node, executor, done=None) -> None:
    """``rclpy.spin`` (or ``spin_until_future_complete`` with ``done``), but never waiting more
    than :data:`WAKE_S` at a time: rclpy's signal handling shuts the context down on SIGINT or
    SIGTERM and wakes the executor's wait, but under load the wake-up was seen lost (a node left
    waiting for ever after SIGTERM: 2 of about 10 loaded stops with a peer); looking at the context again every
    half second ends the node whatever happened to the wake-up.

    rclpy shuts the context down from its signal thread, so it can go down between the loop's
    look and the executor's next step: the step then fails in rclpy (``RCLError`` "failed to
    create timer: the given context is not valid", or a ``RuntimeError`` from a take whose
    subscription is being destroyed).  Such a failure once the context is down, or after
    :data:`INTERRUPTED`, is the stop it is and ends the spin quietly; with the context up it is
    raised."""
    executor.add_node(node)
    if done is not None:
        done.add_done_callback(lambda _: executor.wake())
    try:
        while (executor.context.ok() and not INTERRUPTED.is_set()
               and not (done is not None and done.done())):
            try:
                executor.spin_once(timeout_sec=WAKE_S)
            except RuntimeError as exc:
                # rclpy's RCLError and InvalidHandle, and pybind11's "Unable to convert call
                # argument" of a take during the shutdown (a plain RuntimeError), are RuntimeErrors;
                # its subclasses that are Python's own (recursion, not implemented) are bugs
                if (executor.context.ok() and not INTERRUPTED.is_set()) or isinstance(
                        exc, (RecursionError, NotImplementedError)):
                    raise
                break
    finally:
        executor.remove_node(node)
