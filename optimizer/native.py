"""Compiled NLP functions: CasADi's C code generation, compiled once per machine and cached.

Why
---
CasADi evaluates SX functions in its virtual machine. The same expressions generated as C and
compiled run several times faster: for the shooting NLP of 5 joints (:mod:`.planner.shooting`)
the Hessian of the Lagrangian took 1.6 ms of a 5.4 ms fatrop solve, 0.36 ms compiled, and the
whole plan went from 6.9 to 5.1 ms. Compiling takes seconds (``cc -O1``: about 2.7 s for 3
joints, 5 s for 5), so a compiled library is cached on disk and built at most once per
machine, and by default in the background: until it is ready the virtual machine answers, so
no request waits for a compiler.

How
---
* The key of a library is the SHA-256 of its C source, of the compiler command, of the CasADi
  version and of the platform and machine type (for a cache shared between machines): a
  cached library can never belong to other expressions (a changed model, transcription or
  CasADi version gives other source, hence another key). An NLP's library is keyed by a
  fingerprint of what its source is generated from (:func:`library_for_fingerprint`: its
  serialised expressions and options) instead, so that a process finds it without
  generating the source (0.4-1.3 s at 4 to 7 joints).
* The build runs ``<cc> -O1 -fPIC -shared`` in a separate, detached process (``python -m
  optimizer.native``) that writes a temporary file and renames it into place, so a library is
  either complete or absent; a lock file (naming its machine and builder's PID) keeps two
  processes of one machine from compiling the same key at once, a build asked to wait waits
  for the one under way, a lock whose builder is gone (or that is older than
  :data:`STALE_LOCK`) is taken over, and a failed build leaves a ``.failed`` file (with the
  compiler's messages) so it is not retried.
* Nothing happens until :func:`configure` is called with a directory: a library that starts a
  compiler and writes files only when asked. The service does it in every worker (setting
  ``PLANNER_NATIVE_CACHE``); the benchmark compiles before it measures.

Safety: the cache directory holds code that is loaded into the process. It is created with mode
0700; a directory (or library) that another user owns or may write to is refused.
"""

from __future__ import annotations

import hashlib
import os
import platform
import shutil
import stat
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

#: Flags of the compile (-O1: 5 s for the 5-joint NLP and within 2 % of -O2's speed, which
#: takes 16 s; -O0 compiles in 1.6 s but runs 20 % slower).
FLAGS: tuple[str, ...] = ("-O1", "-fPIC", "-shared")
#: Larger sources are not compiled: cc1's time and memory grow with them (a 1.6 MB source:
#: 5.6 s and 0.29 GB; 10.6 MB, the 6-joint 50-interval NLP: 20 s and 1.6 GB).
MAX_SOURCE_BYTES = 3_000_000
#: A lock older than this (s) belongs to a build that died: it is taken over. Sooner where the
#: lock names its builder on this machine and that process is gone (:func:`_lock_is_stale`).
STALE_LOCK = 300.0


@dataclass(frozen=True)
class NativeConfig:
    """Where compiled libraries live and how they are built.

    Attributes
    ----------
    cache_dir : Path
    compiler : str
        The C compiler's executable (found on ``PATH``).
    """

    cache_dir: Path
    compiler: str


_config: NativeConfig | None = None
#: Keys whose background build this process started.
_builds: set[str] = set()


def default_cache_dir() -> Path:
    """``$XDG_CACHE_HOME/chained-planner/native`` (``~/.cache/...`` when unset)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "chained-planner" / "native"


def configure(cache_dir: str | os.PathLike[str] | None, *,
              compiler: str | None = None) -> NativeConfig | None:
    """Turn compiled NLP functions on (a directory) or off (None) for this process.

    Parameters
    ----------
    cache_dir : path or None
        Directory of the compiled libraries; created (mode 0700) when missing.
    compiler : str, optional
        C compiler; default ``$CC``, else ``cc``, else ``gcc``.

    Returns
    -------
    NativeConfig or None
        None when turned off, or when no compiler is found (then CasADi's virtual machine
        is used, which gives the same results, slower).

    Raises
    ------
    PermissionError
        ``cache_dir`` is writable by other users or owned by another (it holds code that is
    loaded).
    """
    global _config
    if cache_dir is None:
        _config = None
        return None
    cc = _find_compiler(compiler)
    if cc is None:
        _config = None
        return None
    path = Path(cache_dir).expanduser().resolve()
    path.mkdir(mode=0o700, parents=True, exist_ok=True)
    _check_private(path)
    _config = NativeConfig(cache_dir=path, compiler=cc)
    return _config


def _check_private(path: Path) -> None:
    """Refuse a file or directory that another user owns or may write: the cache's libraries
    are loaded into the process, and their names (hashes of the source) can be predicted, so
    a directory others can write to (sticky or not) would let them plant one."""
    st = path.stat()
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise PermissionError(f"native cache path {path} is writable by other users")
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        raise PermissionError(f"native cache path {path} belongs to another user")


def config() -> NativeConfig | None:
    """The current configuration (None: compiled functions are off)."""
    return _config


def _find_compiler(name: str | None) -> str | None:
    for cand in ([name] if name else [os.environ.get("CC"), "cc", "gcc"]):
        if cand:
            found = shutil.which(cand)
            if found:
                return found
    return None


def library_key(source: str, cfg: NativeConfig) -> str:
    """The cache key of a C source under ``cfg``'s compiler (hex, 24 characters)."""
    import casadi as ca

    h = hashlib.sha256()
    for part in (source, cfg.compiler, " ".join(FLAGS), str(getattr(ca, "__version__", "")),
                 sys.platform, platform.machine()):
        h.update(part.encode())
        h.update(b"\0")
    return h.hexdigest()[:24]


def nlp_source(solver: Any, extra: tuple[Any, ...] = ()) -> str:
    """C source of the functions ``solver`` (an ``nlpsol``) evaluates and of its problem, the
    oracle ``nlp(x, p) -> (f, g)``: what ``casadi.nlpsol(name, plugin, library, opts)``
    loads; and of the ``extra`` Functions (``casadi.external(name, library)`` loads each by
    its name)."""
    import casadi as ca

    cg = ca.CodeGenerator("nlp_functions.c", {"with_header": False})
    cg.add(solver.oracle())
    for name in solver.get_function():
        cg.add(solver.get_function(name))
    for f in extra:
        cg.add(f)
    return str(cg.dump())


@dataclass
class Library:
    """One compiled library: ``path`` once it exists."""

    key: str
    cfg: NativeConfig
    last_check: float = 0.0

    @property
    def path(self) -> Path:
        return self.cfg.cache_dir / f"{self.key}.so"

    def ready(self, every: float = 1.0) -> Path | None:
        """The library's path when it is built (checked at most every ``every`` s)."""
        now = time.monotonic()
        if now - self.last_check < every:
            return None
        self.last_check = now
        if not self.path.exists():
            return None
        try:
            _check_private(self.path)
        except PermissionError:
            return None
        return self.path


def library_for(source: str, wait: bool = False) -> Library | None:
    """The library of ``source``: found in the cache, else built now (``wait``: benchmarks,
    an image build) or its build started in the background.

    Returns None when compiled functions are off, the source is larger than
    :data:`MAX_SOURCE_BYTES` or its build failed before (see the ``.failed`` file). Use
    :meth:`Library.ready` to learn when it can be loaded.
    """
    cfg = _config
    if cfg is None or len(source) > MAX_SOURCE_BYTES:
        return None
    return _library(library_key(source, cfg), cfg, lambda: source, wait)


def library_for_fingerprint(fingerprint: str, source: Callable[[], str],
                            wait: bool = False) -> Library | None:
    """:func:`library_for` keyed by ``fingerprint`` instead of the source, which
    ``source()`` generates only when the library is not in the cache.

    Why: an NLP's C source is generated from its solver's derivative functions (the
    Lagrangian's Hessian, the Jacobians), and building those in CasADi's virtual machine and
    writing their C took 0.4-1.3 s at 4 to 7 joints, each process's first plan of each joint
    count, only to find a library that was already built. ``fingerprint`` must determine the
    source as fully as the source determines itself: the serialised expressions the source is
    generated from and every option of the generation (:meth:`MultipleShootingNLP.fingerprint
    <optimizer.planner.nlp.MultipleShootingNLP.fingerprint>`); CasADi's version, the compiler
    and the platform join it in the key as they join a source. A source above
    :data:`MAX_SOURCE_BYTES` leaves a ``.failed`` file, so that it is generated once.
    """
    cfg = _config
    if cfg is None:
        return None
    # (the size limit in the key: a source refused under one limit is tried under another)
    key = library_key(f"fingerprint:{fingerprint}:{MAX_SOURCE_BYTES}", cfg)
    return _library(key, cfg, source, wait)


def _library(key: str, cfg: NativeConfig, source_of: Callable[[], str],
             wait: bool) -> Library | None:
    lib = Library(key, cfg)
    if lib.path.exists():
        return lib
    failed = cfg.cache_dir / f"{lib.key}.failed"
    if failed.exists():
        return None
    source = source_of()
    if len(source) > MAX_SOURCE_BYTES:
        failed.write_text(f"source of {len(source)} bytes, above {MAX_SOURCE_BYTES}: not "
                          "compiled\n")
        return None
    src = cfg.cache_dir / f"{lib.key}.c"
    if not src.exists():
        tmp = src.with_name(f"{src.name}.{os.getpid()}.tmp")
        tmp.write_text(source)
        os.replace(tmp, src)
    entry = [sys.executable, "-m", "optimizer.native"]
    args = [cfg.compiler, str(src), str(lib.path)]
    if wait:
        _run_quiet(entry + args)
        if not lib.path.exists() and _await_other_build(lib, failed):
            _run_quiet(entry + args)  # the other build died: its lock was taken over
        return lib if lib.path.exists() else None
    if not hasattr(os, "fork"):  # no detached build (not POSIX): only builds asked to wait
        return None
    if lib.key not in _builds:
        # Detached (its own session, not our child: a server's shutdown, signals to its
        # process group and measures of its process tree do not touch it, and a finished
        # build is reaped by init) and at niceness +10 on top of ours: it never competes
        # with a solve. The intermediate process exits at once.
        _builds.add(lib.key)
        nice = ["nice", "-n", "10"] if shutil.which("nice") else []
        _run_quiet(nice + entry + ["--detach"] + args)
    return lib


def _await_other_build(lib: Library, failed: Path, poll: float = 0.05) -> bool:
    """Wait while another process holds the build lock of ``lib`` (a fresh one).

    Why: a build asked to wait returns at once when another process builds the same library
    (:func:`build`), and a caller that then ran without it would answer with other code than
    that process: two service workers started together on an empty cache prepared the proofs'
    compiled quadrature, one of them built it, the other ran numpy's for its whole life, and
    the same request got answers differing in the last bits by the worker that served it.

    Returns
    -------
    bool
        True when the wait ended with neither the library nor its ``failed`` file (the lock
        went stale): the caller may build it itself.
    """
    lock = lib.path.with_suffix(".lock")
    while lock.exists() and not lib.path.exists():
        try:
            if _lock_is_stale(lock):
                break
        except OSError:  # released between the two looks
            break
        time.sleep(poll)
    return not lib.path.exists() and not failed.exists()


def _lock_owner() -> str:
    """What a build writes into its lock: this machine's name and the builder's PID."""
    return f"{os.uname().nodename} {os.getpid()}\n"


def _lock_is_stale(lock: Path) -> bool:
    """Whether ``lock`` belongs to a build that died: older than :data:`STALE_LOCK`, or
    written on this machine by a process that no longer runs (a container killed while
    compiling into a persistent cache, a build killed by its session's end: without this,
    every later start waited out :data:`STALE_LOCK`). A lock of another machine (a cache
    shared by pods) is judged by its age alone.

    Raises
    ------
    OSError
        The lock is gone.
    """
    if time.time() - lock.stat().st_mtime >= STALE_LOCK:
        return True
    try:
        host, pid_text = lock.read_text().split()
        pid = int(pid_text)
    except ValueError:  # empty (being written, or of an older version): by its age
        return False
    if host != os.uname().nodename or pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:  # another user's process: it runs
        pass
    return False


def _run_quiet(argv: list[str]) -> None:
    """Run ``argv`` to its end, without its output, with this package importable."""
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    subprocess.run(argv, check=False, env=env, stdin=subprocess.DEVNULL,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def build(compiler: str, source: Path, target: Path) -> int:
    """Compile ``source`` to ``target`` atomically, under a lock; 0 on success.

    Another process holding a fresh lock means the library is on its way: return 0 without
    compiling. A failure writes ``<key>.failed`` with the compiler's messages.
    """
    lock = target.with_suffix(".lock")
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
    except FileExistsError:
        try:
            if not _lock_is_stale(lock):
                return 0
            lock.unlink()
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600)
        except OSError:
            return 0
    try:
        os.write(fd, _lock_owner().encode())
    finally:
        os.close(fd)
    tmp = target.with_name(f"{target.stem}.{os.getpid()}.so.tmp")
    try:
        if target.exists():
            return 0
        res = subprocess.run([compiler, *FLAGS, str(source), "-o", str(tmp)],
                             capture_output=True, text=True, check=False)
        if res.returncode != 0 or not tmp.exists():
            target.with_suffix(".failed").write_text(res.stdout + res.stderr)
            return 1
        os.chmod(tmp, 0o700)  # whatever the umask: only its owner may change what is loaded
        os.replace(tmp, target)
        source.unlink(missing_ok=True)  # 1-3 MB, generated again whenever it is needed
        return 0
    finally:
        tmp.unlink(missing_ok=True)
        lock.unlink(missing_ok=True)


def main(argv: list[str]) -> int:
    """``python -m optimizer.native [--detach] <cc> <source.c> <target.so>``."""
    if argv and argv[0] == "--detach":
        argv = argv[1:]
        if os.fork() > 0:
            os._exit(0)  # the caller waits for this process only
        os.setsid()
    return build(argv[0], Path(argv[1]), Path(argv[2]))


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
