"""Where the diagnosis's independent tasks run: local processes, this process, or a dask
cluster — all behind the ``concurrent.futures.Executor`` interface, so that the candidate
refits (:mod:`identify.diagnosis.rounds`) and the regime screen (:mod:`identify.diagnosis.regime_screen`)
each have one code path whatever runs them."""

from __future__ import annotations

import concurrent.futures as cf

from identify import interrupts

__all__ = ["InProcess", "make_executor", "stop_pool"]


class InProcess(cf.Executor):
    """The Executor interface, run in this process (workers = 1; debugging). Each task
    runs when it is submitted, so its future is already done when ``submit`` returns."""

    def submit(self, fn, *args, **kwargs):
        f: cf.Future = cf.Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except (KeyboardInterrupt, SystemExit):
            raise
        except BaseException as err:  # noqa: BLE001 - handed to the caller through the future
            f.set_exception(err)
        return f


def make_executor(workers: int = 1, dask: str | None = None):
    """(executor, closer): local processes, in-process, or a dask cluster's executor."""
    if dask:
        try:
            from distributed import Client
        except ImportError:
            raise ValueError("--dask needs the optional dependency: pip install 'nanofrictor[dask]'") from None
        client = Client(dask)
        return client.get_executor(), client.close
    if workers <= 1:
        ex = InProcess()
        return ex, ex.shutdown
    import multiprocessing as mp

    # fork where the platform has it: a researcher's script without an
    # ``if __name__ == "__main__"`` guard would run again in every spawned worker; the
    # parent's CasADi thread pools are joined between calls, so forking is safe here
    method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
    ex = cf.ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context(method))

    def close():
        if interrupts.pending():
            stop_pool(ex)
        else:
            ex.shutdown()

    return ex, close


def stop_pool(ex: cf.ProcessPoolExecutor) -> None:
    """Stop a process pool now, its running tasks with it: on an interrupt, a shutdown
    that waits would wait for every running fit, minutes, and so would the interpreter's
    exit (the finished results are in the caller's record already)."""
    procs = list((getattr(ex, "_processes", None) or {}).values())  # (shutdown forgets them)
    ex.shutdown(wait=False, cancel_futures=True)
    for proc in procs:
        proc.terminate()
