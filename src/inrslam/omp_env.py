"""OpenMP wait policy of the CPU kernels: chosen before torch / numba load their OpenMP runtime, adapted to the
machine's load while a run computes.

By default an OpenMP thread that reaches a barrier first *spins* for a while instead of sleeping. Alone on a
machine that saves a wake-up at each of the thousands of parallel regions of an iteration; beside another
CPU-bound process it is a collapse: the spinning thread holds a core the descheduled thread it waits for needs
(measured on 2 cores: 2.6x slower per frame with one busy process, 5x with two). A passive policy sleeps at once:
no collapse, but every region pays a wake-up (1.1-1.8x slower per frame alone). The runtime reads the policy once,
when it loads, so it is chosen here, at `import inrslam`:

- `OMP_WAIT_POLICY` set by the user: kept as given.
- `INRSLAM_OMP_WAIT=runtime`: the runtime's default (spin, then sleep), never throttled.
- `INRSLAM_OMP_WAIT=passive`: `OMP_WAIT_POLICY=PASSIVE` (if torch was imported first, runs hold the throttle below
  from start to end instead).
- otherwise (`adaptive`, the default where torch's OpenMP runtime is GNU libgomp, as in the Linux wheels): the
  runtime's default, and while a run computes, `load_guard` watches how much CPU *other* processes use; while they
  would oversubscribe the cores it makes every libgomp in the process wait as if passive (below), and lets it spin
  again once the load is gone. Where torch's runtime is another one (macOS, some conda builds), or `OMP_DYNAMIC` /
  `OMP_THREAD_LIMIT` is set (libgomp may then shrink the throttle's threads), `PASSIVE`.
- torch imported before inrslam: the runtime's default has been read already; `load_guard` adapts it if torch's
  runtime is libgomp.

How the guard switches a running libgomp: a thread waiting at a barrier spins `GOMP_SPINCOUNT` times (300 000 by
default) before it sleeps, but only 100 times when the runtime manages more threads than the CPUs it may use.
Entering one parallel region of `cores + 1` threads from a helper thread (the *ballast*: its threads do nothing and
sleep) raises that count above the CPUs; ending the helper thread frees its threads and lowers it again. Where the
load cannot be read (no /proc/stat), the guard holds the ballast for the whole block: passive, as is safe. The
policy changes when threads sleep, never how work is split: results are the same under any policy and with or
without the ballast (tested).
"""

from __future__ import annotations

import ctypes
import glob
import importlib.util
import os
import sys
import threading
import time
import warnings
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator, Optional

ENV = "OMP_WAIT_POLICY"
OPT_OUT = "INRSLAM_OMP_WAIT"  # "runtime": spin, then sleep; "passive": always sleep; "adaptive" / unset: the guard
CHOICES = ("adaptive", "passive", "runtime")
DEFAULT = "PASSIVE"
_origin = "unset"
MARK = "INRSLAM_OMP_WAIT_SET"  # the OMP_WAIT_POLICY value inrslam itself set, so that child processes (sweep workers)
# that inherit the variable still say inrslam set it, not the user
_adaptive = False  # runs adapt the wait to the load (`load_guard`)
_always = False  # runs hold the throttle from start to end (passive asked for after torch loaded)

# the guard's thresholds, in cores: other processes' CPU use beyond the cores this run leaves free, averaged over one
# sampling interval
ENGAGE_LOAD = 0.5  # at or above: throttle the spinning
RELEASE_LOAD = 0.25  # below this for RELEASE_SAMPLES consecutive samples: spin again
RELEASE_SAMPLES = 4
INTERVAL_S = 0.25  # seconds between samples
JOIN_TIMEOUT_S = 5.0  # seconds to wait for a helper thread to start or end
THREAD_MARGIN = 64  # threads that must stay available under the process's limits after the ballast's


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
    others = glob.glob(os.path.join(lib, "libiomp5*")) + glob.glob(os.path.join(lib, "libomp*"))
    return bool(glob.glob(os.path.join(lib, "libgomp*"))) and not others


def _omp_limits_set() -> bool:
    """OMP_DYNAMIC or OMP_THREAD_LIMIT set: libgomp may give the ballast fewer threads than it asks for."""
    return os.environ.get("OMP_DYNAMIC", "").strip().lower() in ("true", "1", "yes") or "OMP_THREAD_LIMIT" in os.environ


def apply_wait_policy() -> str:
    """Choose the wait policy (module docstring) if no OpenMP runtime is loaded yet; returns who chose it."""
    global _origin, _adaptive, _always
    choice = os.environ.get(OPT_OUT, "").strip().lower()
    if choice and choice not in CHOICES:
        warnings.warn(f"{OPT_OUT}={choice!r} is not one of {', '.join(CHOICES)}: using adaptive", stacklevel=2)
        choice = "adaptive"
    loaded = "torch" in sys.modules or "numba" in sys.modules
    libgomp = _torch_runtime_is_libgomp() and not _omp_limits_set()
    _adaptive = _always = False
    if ENV in os.environ:
        mine = _origin == "inrslam" or os.environ.get(MARK) == os.environ[ENV]
        _origin = "inrslam" if mine else "user"
    elif choice == "runtime":
        _origin = f"runtime default ({OPT_OUT}=runtime)"
    elif loaded and choice == "passive":
        _origin = "runtime default (torch imported before inrslam), throttled for whole runs"
        _adaptive = _always = libgomp
    elif loaded:
        _origin = "runtime default (torch imported before inrslam)" + (", adaptive" if libgomp else "")
        _adaptive = libgomp
    elif choice != "passive" and libgomp:
        _origin, _adaptive = "inrslam (adaptive)", True
    else:
        os.environ[ENV] = os.environ[MARK] = DEFAULT
        _origin = "inrslam"
    return _origin


def wait_policy() -> dict:
    """{'policy': the OMP_WAIT_POLICY in effect (None: the runtime's default, spinning), 'set_by': who set it,
    'adaptive': whether runs throttle the spinning under load, 'guard': the counts of the last guarded block}."""
    return {"policy": os.environ.get(ENV), "set_by": _origin, "adaptive": _adaptive, "guard": _GUARD.stats()}


# -- measuring other processes' load ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class CpuSample:
    """One reading: wall clock (s), busy CPU time of the cores this process may use (s), this process's CPU time (s)."""

    wall: float
    busy: float
    own: float


def _busy_ticks(vals: list[str]) -> int:
    v = [int(x) for x in vals[:8]]  # user nice system idle iowait irq softirq steal
    return v[0] + v[1] + v[2] + v[5] + v[6] + v[7]


def parse_proc_stat(text: str, cpus: set[int], ticks_per_s: float) -> Optional[float]:
    """Busy seconds (user, nice, system, irq, softirq, steal) summed over the `cpuN` lines of /proc/stat whose N is in
    `cpus`; where none of them is listed (a container's /proc numbering its own cores from 0), the all-core `cpu`
    line; None if unreadable."""
    total, seen, aggregate = 0, False, None
    try:
        for line in text.splitlines():
            if not line.startswith("cpu"):
                continue
            name, *vals = line.split()
            if len(vals) < 8:
                continue
            if name == "cpu":
                aggregate = _busy_ticks(vals)
            elif name[3:].isdigit() and int(name[3:]) in cpus:
                total += _busy_ticks(vals)
                seen = True
    except ValueError:
        return None
    if seen:
        return total / ticks_per_s
    return aggregate / ticks_per_s if aggregate is not None else None


def other_load(a: CpuSample, b: CpuSample) -> float:
    """Cores' worth of CPU time that other processes used between samples a and b (>= 0)."""
    dt = b.wall - a.wall
    if dt <= 0:
        return 0.0
    return max(0.0, ((b.busy - a.busy) - (b.own - a.own)) / dt)


def next_state(engaged: bool, calm: int, load: float) -> tuple[bool, int]:
    """The guard's hysteresis: (engaged, consecutive calm samples) after a sample with `load` cores of other
    processes beyond the free ones. Engages at once at ENGAGE_LOAD; releases after RELEASE_SAMPLES samples below
    RELEASE_LOAD."""
    if load >= ENGAGE_LOAD:
        return True, 0
    if not engaged:
        return False, 0
    calm = calm + 1 if load < RELEASE_LOAD else 0
    return (False, 0) if calm >= RELEASE_SAMPLES else (True, calm)


def cpu_set() -> set[int]:
    """The cores this process may run on (its affinity mask where the OS has one, else all of the CPU count)."""
    try:
        return set(os.sched_getaffinity(0)) or {0}
    except (AttributeError, OSError):
        return set(range(max(1, os.cpu_count() or 1)))


def _proc_sampler() -> Callable[[], Optional[CpuSample]]:
    """Readings from /proc/stat (the cores in this process's affinity mask) and os.times() (this process)."""
    ticks = float(os.sysconf("SC_CLK_TCK")) if hasattr(os, "sysconf") else 100.0

    def read() -> Optional[CpuSample]:
        try:
            with open("/proc/stat") as f:
                busy = parse_proc_stat(f.read(), cpu_set(), ticks)
        except OSError:
            return None
        if busy is None:
            return None
        t = os.times()
        return CpuSample(time.monotonic(), busy, t.user + t.system)

    return read


def _run_threads() -> int:
    """Threads a run computes with: torch's intra-op count in the calling thread where torch is loaded, else every
    core."""
    torch = sys.modules.get("torch")
    try:
        return int(torch.get_num_threads()) if torch is not None else len(cpu_set())
    except Exception:  # a half-imported torch: assume every core
        return len(cpu_set())


# -- the ballast ----------------------------------------------------------------------------------------------------
def loaded_libgomp() -> list[str]:
    """Paths of the GNU OpenMP runtimes loaded in this process (torch ships its own; numba may load the system's)."""
    out = set()
    try:
        with open("/proc/self/maps") as f:
            for line in f:
                if "libgomp" not in line:
                    continue
                parts = line.split(maxsplit=5)
                path = parts[5].strip() if len(parts) == 6 else ""
                base = os.path.basename(path)
                if base.startswith("libgomp") and "plugin" not in base:
                    out.add(path)
    except OSError:
        return []
    return sorted(out)


def thread_headroom() -> Optional[int]:
    """Threads this process may still start under its cgroup's pids.max (cgroup v2) and RLIMIT_NPROC's soft limit
    (which also counts the user's other threads: only its size is used); None where neither limit is known."""
    room: list[int] = []
    own = len(os.listdir("/proc/self/task")) if os.path.isdir("/proc/self/task") else 0
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_NPROC)[0]
        if soft != resource.RLIM_INFINITY:
            room.append(int(soft) - own)
    except (ImportError, OSError, ValueError):
        pass
    try:
        with open("/proc/self/cgroup") as f:
            rel = next((line.split(":", 2)[2].strip() for line in f if line.startswith("0::")), None)
        if rel is not None:
            base = os.path.join("/sys/fs/cgroup", rel.lstrip("/"))
            with open(os.path.join(base, "pids.max")) as f:
                limit = f.read().strip()
            if limit != "max":
                with open(os.path.join(base, "pids.current")) as f:
                    room.append(int(limit) - int(f.read().strip()))
    except (OSError, ValueError, StopIteration):
        pass
    return min(room) if room else None


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
        """Start the helper thread and wait until its regions were entered."""
        self._thread.start()
        self._ready.wait(JOIN_TIMEOUT_S)
        return self

    def stop(self) -> None:
        """End the helper thread (libgomp then frees the ballast's threads)."""
        self._stop.set()
        self._thread.join(JOIN_TIMEOUT_S)


class LoadGuard:
    """While at least one `load_guard()` block is open, samples other processes' load every `interval` seconds and
    holds a `Ballast` while they would oversubscribe the cores (`next_state`; `always`: from start to end)."""

    def __init__(self, sample: Optional[Callable[[], Optional[CpuSample]]] = None, interval: float = INTERVAL_S,
                 always: bool = False):
        """sample: returns one reading (None: cannot read; the guard then holds the ballast), default /proc/stat and
        os.times(); interval: seconds between readings; always: hold the ballast whatever the load."""
        self._sample = sample or _proc_sampler()
        self.interval = interval
        self.always = always
        self._lock = threading.Lock()
        self._users = 0
        self._stop = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._ballast: Optional[Ballast] = None
        self.samples = 0
        self.throttled_samples = 0
        self.switches = 0
        self.failed: Optional[str] = None
        self.run_threads = 0  # threads of the guarded run (set on entry)

    def stats(self) -> dict:
        """Counts of the current or last guarded block: readings, readings while throttled, ballasts started."""
        out: dict = {"samples": self.samples, "throttled_samples": self.throttled_samples, "switches": self.switches}
        if self.failed:
            out["failed"] = self.failed
        return out

    @property
    def throttled(self) -> bool:
        """Whether a ballast is held now."""
        return self._ballast is not None and bool(self._ballast.held)

    def engage(self) -> None:
        """Hold a ballast in every loaded libgomp (again if one was loaded since)."""
        libs = loaded_libgomp()
        if self._ballast is not None and self._ballast.libs == libs:
            return
        self.release()
        cores = len(cpu_set())
        room = thread_headroom()
        if libs and (room is None or room >= len(libs) * (cores + 1) + THREAD_MARGIN):
            self._ballast = Ballast(libs, cores + 1).start()
            self.switches += 1

    def release(self) -> None:
        """Let the ballast's threads go (the runtimes spin again)."""
        if self._ballast is not None:
            self._ballast.stop()
            self._ballast = None

    def _watch(self, stop: threading.Event) -> None:
        try:
            prev = None if self.always else self._sample()
            engaged, calm = prev is None, 0  # no first reading (or asked to): throttled for the whole block
            if engaged:
                self.engage()
            while not stop.wait(self.interval):
                cur = None if prev is None else self._sample()
                if prev is None or cur is None:
                    engaged = True  # unreadable: stay on the safe side
                else:
                    spare = max(0, len(cpu_set()) - self.run_threads)  # cores this run leaves to others
                    engaged, calm = next_state(engaged, calm, other_load(prev, cur) - spare)
                    prev = cur
                if engaged:
                    self.engage()  # again each time: a runtime loaded since (numba's) is throttled too
                else:
                    self.release()
                self.samples += 1
                self.throttled_samples += int(self.throttled)
        except Exception as e:  # never let the guard disturb a run: stop guarding, say why in run_info.json
            self.failed = f"{type(e).__name__}: {e}"
        finally:
            self.release()

    def enter(self) -> None:
        """Open a guarded block (the first one starts the watcher and resets the counts)."""
        with self._lock:
            self._users += 1
            if self._users == 1:
                self.samples = self.throttled_samples = self.switches = 0
                self.failed = None
                self.run_threads = _run_threads()  # read here: torch's count is the calling thread's
                self._stop = threading.Event()  # a watcher of an earlier block keeps its own
                self._thread = threading.Thread(target=self._watch, args=(self._stop,), name="inrslam-omp-guard",
                                                daemon=True)
                self._thread.start()

    def exit(self) -> None:
        """Close a guarded block (the last one stops the watcher, which lets the ballast go)."""
        with self._lock:
            self._users = max(0, self._users - 1)
            if self._users == 0 and self._thread is not None:
                self._stop.set()
                self._thread.join(2 * JOIN_TIMEOUT_S + self.interval)
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
    guard = _GUARD
    active = _adaptive and sys.platform.startswith("linux")
    if active:
        guard.always = _always
        guard.enter()
    try:
        yield guard
    finally:
        if active:
            guard.exit()
