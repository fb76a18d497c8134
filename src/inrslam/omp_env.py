"""OpenMP wait policy of the CPU kernels: chosen before torch / numba load their OpenMP runtime, adapted to the
machine's load while a run computes.

By default an OpenMP thread that reaches a barrier first *spins* for a while instead of sleeping. Alone on a
machine that saves a wake-up at each of the thousands of parallel regions of an iteration; beside another
CPU-bound process it is a collapse: the spinning thread holds a core the descheduled thread it waits for needs
(measured on 2 cores: 2.6x slower per frame with one busy process, 5x with two). A passive policy sleeps at once:
no collapse, but every region pays a wake-up (1.1-1.8x slower per frame alone). The runtime reads the policy once,
when it loads, so it is chosen here, at `import inrslam`:

- `OMP_WAIT_POLICY` set by the user: kept as given.
- `INRSLAM_OMP_WAIT=runtime`: the runtime's default (spin, then sleep), always.
- `INRSLAM_OMP_WAIT=passive`: `OMP_WAIT_POLICY=PASSIVE`, always.
- otherwise (`adaptive`, the default where torch's OpenMP runtime is GNU libgomp, as in the Linux wheels): the
  runtime's default, and while a run computes, `load_guard` watches how much CPU *other* processes use; under
  load it makes every libgomp in the process wait as if passive (below), and lets it spin again once the load is
  gone. Where the runtime is another one (macOS, some conda builds), `PASSIVE`.
- torch imported before inrslam: the runtime's default has been read already; `load_guard` still adapts it.

How the guard switches a running libgomp: a thread waiting at a barrier spins `GOMP_SPINCOUNT` times (300 000 by
default) before it sleeps, but only 100 times when the runtime manages more threads than the CPUs it may use.
Entering one parallel region of `cores + 1` threads from a helper thread (the *ballast*: its threads do nothing and
sleep) raises that count above the CPUs; ending the helper thread frees its threads and lowers it again. The policy
changes when threads sleep, never how work is split: results are the same under any policy and with or without the
ballast (tested).
"""

from __future__ import annotations

import ctypes
import glob
import importlib.util
import os
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator, Optional

ENV = "OMP_WAIT_POLICY"
OPT_OUT = "INRSLAM_OMP_WAIT"  # "runtime": spin, then sleep; "passive": always sleep; "adaptive" / unset: the guard
DEFAULT = "PASSIVE"
_origin = "unset"
_adaptive = False

# the guard's thresholds: other processes' CPU use in cores, averaged over one sampling interval
ENGAGE_LOAD = 0.5  # at or above: throttle the spinning
RELEASE_LOAD = 0.25  # below this for RELEASE_SAMPLES consecutive samples: spin again
RELEASE_SAMPLES = 4
INTERVAL_S = 0.25  # seconds between samples


def _torch_runtime_is_libgomp() -> bool:
    """True if the torch that would be imported ships GNU libgomp as its OpenMP runtime (found without importing
    torch, which would load it)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        spec = importlib.util.find_spec("torch")
    except (ImportError, ValueError):
        return False
    if spec is None or not spec.submodule_search_locations:
        return False
    lib = os.path.join(list(spec.submodule_search_locations)[0], "lib")
    others = glob.glob(os.path.join(lib, "libiomp5*")) + glob.glob(os.path.join(lib, "libomp.*"))
    return bool(glob.glob(os.path.join(lib, "libgomp*"))) and not others


def apply_wait_policy() -> str:
    """Choose the wait policy (module docstring) if no OpenMP runtime is loaded yet; returns who chose it."""
    global _origin, _adaptive
    choice = os.environ.get(OPT_OUT, "").lower()
    if ENV in os.environ:
        _origin = "user" if _origin != "inrslam" else _origin
        _adaptive = False
    elif choice == "runtime":
        _origin, _adaptive = f"runtime default ({OPT_OUT}=runtime)", False
    elif "torch" in sys.modules or "numba" in sys.modules:
        _origin, _adaptive = "runtime default (torch imported before inrslam), adaptive", True
    elif choice != "passive" and _torch_runtime_is_libgomp():
        _origin, _adaptive = "inrslam (adaptive)", True
    else:
        os.environ[ENV] = DEFAULT
        _origin, _adaptive = "inrslam", False
    return _origin


def wait_policy() -> dict:
    """{'policy': the OMP_WAIT_POLICY in effect (None: the runtime's default, spinning), 'set_by': who set it,
    'adaptive': whether runs throttle the spinning under load, 'guard': the guard's counts so far}."""
    return {"policy": os.environ.get(ENV), "set_by": _origin, "adaptive": _adaptive, "guard": _GUARD.stats()}


# -- measuring other processes' load ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class CpuSample:
    """One reading: wall clock (s), busy CPU time of the cores this process may use (s), this process's CPU time (s)."""

    wall: float
    busy: float
    own: float


def parse_proc_stat(text: str, cpus: set[int], ticks_per_s: float) -> Optional[float]:
    """Busy seconds (user, nice, system, irq, softirq, steal) summed over the `cpuN` lines of /proc/stat whose N is in
    `cpus`; None if none of them is there."""
    total, seen = 0, False
    for line in text.splitlines():
        if not line.startswith("cpu") or line.startswith("cpu "):
            continue
        name, *vals = line.split()
        try:
            n = int(name[3:])
        except ValueError:
            continue
        if n not in cpus or len(vals) < 8:
            continue
        v = [int(x) for x in vals[:8]]  # user nice system idle iowait irq softirq steal
        total += v[0] + v[1] + v[2] + v[5] + v[6] + v[7]
        seen = True
    return total / ticks_per_s if seen else None


def other_load(a: CpuSample, b: CpuSample) -> float:
    """Cores' worth of CPU time that other processes used between samples a and b (>= 0)."""
    dt = b.wall - a.wall
    if dt <= 0:
        return 0.0
    return max(0.0, ((b.busy - a.busy) - (b.own - a.own)) / dt)


def next_state(engaged: bool, calm: int, load: float) -> tuple[bool, int]:
    """The guard's hysteresis: (engaged, consecutive calm samples) after a sample with `load` cores of other
    processes. Engages at once at ENGAGE_LOAD; releases after RELEASE_SAMPLES samples below RELEASE_LOAD."""
    if load >= ENGAGE_LOAD:
        return True, 0
    if not engaged:
        return False, 0
    calm = calm + 1 if load < RELEASE_LOAD else 0
    return (False, 0) if calm >= RELEASE_SAMPLES else (True, calm)


def _proc_sampler() -> Callable[[], Optional[CpuSample]]:
    """Readings from /proc/stat (the cores in this process's affinity mask) and os.times() (this process)."""
    cpus = set(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else set()
    ticks = float(os.sysconf("SC_CLK_TCK")) if hasattr(os, "sysconf") else 100.0

    def read() -> Optional[CpuSample]:
        try:
            with open("/proc/stat") as f:
                busy = parse_proc_stat(f.read(), cpus, ticks)
        except OSError:
            return None
        if busy is None:
            return None
        t = os.times()
        return CpuSample(time.monotonic(), busy, t.user + t.system)

    return read


# -- the ballast ----------------------------------------------------------------------------------------------------
def loaded_libgomp() -> list[str]:
    """Paths of the GNU OpenMP runtimes loaded in this process (torch ships its own; numba may load the system's)."""
    try:
        with open("/proc/self/maps") as f:
            return sorted({line.split()[-1] for line in f if os.path.basename(line.split()[-1]).startswith("libgomp")
                           and "/" in line})
    except OSError:
        return []


class Ballast:
    """A helper thread that entered one parallel region of `threads` threads in each given libgomp and waits: while it
    lives, each runtime manages more threads than there are CPUs and throttles its spinning."""

    def __init__(self, libs: list[str], threads: int):
        self.libs = list(libs)
        self.held: list[str] = []  # the runtimes whose region was entered
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._thread = threading.Thread(target=self._hold, args=(threads,), name="inrslam-omp-ballast", daemon=True)

    def _hold(self, threads: int) -> None:
        try:
            free = ctypes.cast(ctypes.CDLL(None).free, ctypes.c_void_p).value  # free(NULL): each thread's empty body
            for path in self.libs:
                try:
                    par = ctypes.CDLL(path).GOMP_parallel
                except (OSError, AttributeError):
                    continue
                par.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint, ctypes.c_uint]
                par.restype = None
                par(free, None, threads, 0)
                self.held.append(path)
        except (OSError, AttributeError, TypeError):  # no libc symbol here: nothing is held, the run goes on
            pass
        self._ready.set()
        self._stop.wait()  # returning ends the thread: libgomp frees its pools and their threads

    def start(self) -> "Ballast":
        self._thread.start()
        self._ready.wait(5.0)
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5.0)


class LoadGuard:
    """Samples other processes' load every INTERVAL_S seconds while at least one `load_guard()` block is open, and
    holds a `Ballast` while they load the machine (`next_state`)."""

    def __init__(self, sample: Optional[Callable[[], Optional[CpuSample]]] = None, interval: float = INTERVAL_S):
        """sample: returns one reading (None: cannot read; the guard stops), default /proc/stat and os.times();
        interval: seconds between readings."""
        self._sample = sample or _proc_sampler()
        self.interval = interval
        self._lock = threading.Lock()
        self._users = 0
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._ballast: Optional[Ballast] = None
        self.samples = 0
        self.throttled_samples = 0
        self.switches = 0

    def stats(self) -> dict:
        return {"samples": self.samples, "throttled_samples": self.throttled_samples, "switches": self.switches}

    @property
    def throttled(self) -> bool:
        return self._ballast is not None

    def engage(self) -> None:
        """Hold a ballast in every loaded libgomp (again if one was loaded since)."""
        libs = loaded_libgomp()
        if self._ballast is not None and self._ballast.libs == libs:
            return
        self.release()
        if libs:
            cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
            self._ballast = Ballast(libs, cores + 1).start()
            self.switches += 1

    def release(self) -> None:
        if self._ballast is not None:
            self._ballast.stop()
            self._ballast = None

    def _watch(self) -> None:
        prev = self._sample()
        engaged, calm = False, 0
        while prev is not None and not self._stop.wait(self.interval):
            cur = self._sample()
            if cur is None:
                break
            engaged, calm = next_state(engaged, calm, other_load(prev, cur))
            prev = cur
            self.samples += 1
            self.throttled_samples += int(engaged)
            if engaged:
                self.engage()
            else:
                self.release()
        self.release()

    def enter(self) -> None:
        with self._lock:
            self._users += 1
            if self._users == 1:
                self._stop.clear()
                self._thread = threading.Thread(target=self._watch, name="inrslam-omp-guard", daemon=True)
                self._thread.start()

    def exit(self) -> None:
        with self._lock:
            self._users -= 1
            if self._users == 0 and self._thread is not None:
                self._stop.set()
                self._thread.join(5.0)
                self._thread = None


_GUARD = LoadGuard()


def _after_fork_in_child() -> None:
    global _GUARD
    _GUARD = LoadGuard()  # the parent's threads do not exist here


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


@contextmanager
def load_guard() -> Iterator[LoadGuard]:
    """Adapt the wait to the machine's load while the block runs (only with the adaptive policy on Linux; otherwise
    a no-op). Nested and concurrent blocks share one guard."""
    active = _adaptive and sys.platform.startswith("linux") and hasattr(os, "sched_getaffinity")
    if active:
        _GUARD.enter()
    try:
        yield _GUARD
    finally:
        if active:
            _GUARD.exit()
