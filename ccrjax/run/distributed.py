"""Several processes (on one machine or several) training one grid: ``jax.distributed``.

A grid command started as ``N`` processes with ``--coordinator HOST:PORT --num-processes N
--process-id I`` (or ``--distributed``, where a cluster's environment tells JAX all three)
joins them into one JAX job before anything touches a device: every process then sees the
devices of all of them, the grid's runs axis is sharded over that global mesh
(:mod:`ccrjax.training.grid`), each process trains the runs on its own devices, and every
process receives all results (``process_allgather``). Process 0 writes the results; every
process writes its share of a checkpoint (orbax), into the same folder, so the folder must be
one they all see (one machine, or a shared file system).

JAX's coordination service ends a process with a fatal error, not an exception, when the
coordinator cannot be reached or the processes do not add up; so before it starts, the
processes meet once on the coordinator's port by a handshake of our own (process 0 listens,
the others say their id and count) and a mistake is one line and exit status 2:
an unreachable coordinator, counts that differ, an id used twice, a process that never
came. On CPU the collectives go through gloo.
"""

from __future__ import annotations

import argparse
import json
import socket
import time
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils

from ccrjax import cli

DEFAULT_TIMEOUT_S = 120.0


def add_options(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(
        "several processes (jax.distributed)",
        "Start the same command once per process, each with its --process-id; process 0 "
        "writes the results, every process trains its share of each grid.")
    group.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                       help="process 0's address and a free port (every process the same)")
    group.add_argument("--num-processes", type=cli.positive_int, default=None,
                       help="how many processes take part (every process the same)")
    group.add_argument("--process-id", type=int, default=None,
                       help="this process's number, 0 to --num-processes - 1")
    group.add_argument("--distributed", action="store_true",
                       help="take all three from the cluster's environment (SLURM, Open MPI, "
                       "...), as jax.distributed.initialize() does")
    group.add_argument("--distributed-timeout", type=cli.positive_float,
                       default=DEFAULT_TIMEOUT_S,
                       help="seconds to wait for the other processes (default: %(default)g)")


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise cli.UsageError(f"--coordinator {text!r}: give HOST:PORT, a port 1-65535")
    return host, int(port)


def check(args: argparse.Namespace) -> tuple[str, int, int, int] | None:
    """The coordinator's host and port, the process count and this process's id, or
    ``None`` for one process; raises :class:`ccrjax.cli.UsageError` for what does not add up."""
    given = {"--coordinator": args.coordinator, "--num-processes": args.num_processes,
             "--process-id": args.process_id}
    if not any(v is not None for v in given.values()):
        return None
    missing = [name for name, value in given.items() if value is None]
    if missing:
        raise cli.UsageError(f"{', '.join(missing)} missing: several processes need "
                             "--coordinator, --num-processes and --process-id together")
    if args.distributed:
        raise cli.UsageError("--distributed takes the processes from the cluster: give it "
                             "or --coordinator/--num-processes/--process-id, not both")
    if not 0 <= args.process_id < args.num_processes:
        raise cli.UsageError(f"--process-id {args.process_id}: must be 0 to "
                             f"{args.num_processes - 1} (--num-processes {args.num_processes})")
    host, port = _address(args.coordinator)
    return host, port, args.num_processes, args.process_id


def _send(connection: socket.socket, message: dict[str, Any]) -> None:
    connection.sendall(json.dumps(message).encode() + b"\n")


def _receive(connection: socket.socket) -> dict[str, Any]:
    data = b""
    while not data.endswith(b"\n"):
        chunk = connection.recv(4096)
        if not chunk:
            raise ConnectionError("the connection closed")
        data += chunk
    return json.loads(data)


def _host(host: str, port: int, count: int, timeout_s: float) -> None:
    """Process 0: waits for the ``count - 1`` others on the coordinator's port and checks
    that their counts and ids add up; tells each whether to go on."""
    server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        server.bind(("", port))
    except OSError as error:
        raise cli.UsageError(f"--coordinator: cannot listen on port {port} ({error.strerror}): "
                             "choose a free port") from None
    server.listen(count)
    deadline = time.monotonic() + timeout_s
    joined: dict[int, socket.socket] = {}
    problem = None
    try:
        while len(joined) < count - 1 and problem is None:
            server.settimeout(max(0.01, deadline - time.monotonic()))
            try:
                connection, _ = server.accept()
            except TimeoutError:
                problem = (f"{len(joined) + 1} of {count} processes came within "
                           f"{timeout_s:g} s (ids {sorted([0, *joined])}): start the others "
                           "with the same --coordinator, or raise --distributed-timeout")
                break
            hello = _receive(connection)
            if hello["count"] != count:
                problem = (f"process {hello['id']} says --num-processes {hello['count']}, "
                           f"process 0 {count}: give every process the same")
            elif hello["id"] in joined or hello["id"] == 0:
                problem = f"--process-id {hello['id']} given to two processes"
            joined[hello["id"]] = connection
        for connection in joined.values():
            _send(connection, {"ok": problem is None, "problem": problem})
            connection.close()
    finally:
        server.close()
    if problem:
        raise cli.UsageError(problem)


def _join(host: str, port: int, count: int, process_id: int, timeout_s: float) -> None:
    """A process other than 0: says its id and count to process 0 and waits for its go."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            connection = socket.create_connection((host, port), timeout=5.0)
            break
        except OSError:
            if time.monotonic() > deadline:
                raise cli.UsageError(f"--coordinator {host}:{port} not reachable within "
                                     f"{timeout_s:g} s: start process 0 there, or check the "
                                     "address") from None
            time.sleep(0.2)
    with connection:
        _send(connection, {"id": process_id, "count": count})
        connection.settimeout(max(1.0, deadline - time.monotonic() + 5.0))
        try:
            answer = _receive(connection)
        except (OSError, ValueError):
            raise cli.UsageError(f"process 0 at {host}:{port} did not answer: check that "
                                 "every process was given the same --coordinator") from None
    if not answer["ok"]:
        raise cli.UsageError(answer["problem"])


def initialize(prog: str, args: argparse.Namespace) -> None:
    """Joins this process to the job ``args`` describe (nothing for one process); a mistake
    ends the command with one line and status 2. Call before anything touches a device."""
    try:
        found = check(args)
    except cli.UsageError as error:
        cli.fail(prog, str(error))
    if found is None and not args.distributed:
        return
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    timeout_s = args.distributed_timeout
    if args.distributed:
        try:
            jax.distributed.initialize(initialization_timeout=int(timeout_s))
        except (RuntimeError, ValueError) as error:
            cli.fail(prog, f"--distributed: {str(error).splitlines()[0]}")
        return
    host, port, count, process_id = found
    try:
        if process_id == 0:
            _host(host, port, count, timeout_s)
        else:
            _join(host, port, count, process_id, timeout_s)
    except cli.UsageError as error:
        cli.fail(prog, str(error))
    jax.distributed.initialize(f"{host}:{port}", num_processes=count, process_id=process_id,
                               initialization_timeout=int(timeout_s))


def is_primary() -> bool:
    """Whether this process writes the results (process 0, or the only one)."""
    return jax.process_index() == 0


def agree(flag: bool) -> bool:
    """Process 0's ``flag`` in every process (a collective: every process calls it at the
    same point), so that a decision taken from a clock is taken alike."""
    if jax.process_count() == 1:
        return flag
    return bool(multihost_utils.broadcast_one_to_all(np.asarray(flag)))


def barrier(name: str) -> None:
    """Waits until every process reaches the barrier ``name``."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)
