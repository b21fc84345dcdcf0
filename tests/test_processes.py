"""The local worker pool (:class:`sb3_cql.processes.WorkerPool`) stops whatever its workers were doing."""

import subprocess
import sys
import textwrap

# Five pools, each left by an exception while its two workers send results of 4 MB (a pipe's buffer holds 64 kB): a
# worker is killed halfway through a result almost every time.
LEFT_MID_RESULT = textwrap.dedent(
    """
    from concurrent.futures.process import BrokenProcessPool

    from sb3_cql.processes import WorkerPool

    for trial in range(5):
        try:
            with WorkerPool(2) as pool:
                futures = [pool.submit(bytes, 4_000_000) for _ in range(40)]
                futures[1].result()
                raise KeyboardInterrupt
        except KeyboardInterrupt:
            pass
        assert all(future.done() for future in futures), trial  # each with its result, or failed
        assert any(isinstance(future.exception(), BrokenProcessPool) for future in futures), trial
    print("stopped")
    """
)


def test_a_pool_left_by_an_exception_stops_though_its_workers_die_halfway_through_sending_a_result():
    run = subprocess.run([sys.executable, "-c", LEFT_MID_RESULT], capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert run.stdout == "stopped\n"
