"""Sessions' windows taken by a `StreamBatcher` as one batch, as `serve` takes the windows that are due together."""

import threading


def one_batch(batcher, sessions, chunk, errors: list) -> dict:
    """Each session whose `errors` entry is None hears `chunk` and submits it as a window while the batcher is held,
    so they are taken as one batch -> {index: its frames}; a window that fails leaves its exception in `errors`."""
    gate = threading.Event()
    batcher.submit_ranked(0.0, gate.wait)  # holds the batcher: the windows queue behind it
    futures = {}
    for k, s in enumerate(sessions):
        if errors[k] is None:
            s._hear(chunk)
            futures[k] = batcher.submit_push(s, chunk)
    gate.set()
    done = {}
    for k, f in futures.items():
        if (e := f.exception(timeout=60)) is not None:
            errors[k] = e
        else:
            done[k] = f.result()
    return done
