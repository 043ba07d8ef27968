"""Wall-clock timing shared by the benchmarks: the machines are shared and noisy, so every
figure is the best of several runs, and calls compared with each other alternate."""

from __future__ import annotations

import time
from collections.abc import Callable, Hashable, Mapping
from typing import TypeVar

Key = TypeVar("Key", bound=Hashable)


def best_of(fn: Callable[[], object], repeats: int) -> float:
    """The fastest of ``repeats`` wall-clock runs, in seconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def alternating_best(
    calls: Mapping[Key, Callable[[], object]],
    repeats: int,
    progress: str | None = None,
    warm_up: bool = True,
    inspect: Callable[[Key, object], None] | None = None,
) -> dict[Key, float]:
    """Seconds per call, the best of ``repeats`` rounds in which the calls take turns (noise
    hits them alike), after one warm-up call each (library builds, caches; ``warm_up=False``
    when the caller has made it); ``progress``: a progress bar's label; ``inspect(key,
    result)``, if given, sees every call's result, outside the timed interval."""
    from tqdm.auto import tqdm

    for call in calls.values() if warm_up else ():
        call()
    best = {key: float("inf") for key in calls}
    for _ in tqdm(range(repeats), desc=progress, disable=progress is None):
        for key, call in calls.items():
            start = time.perf_counter()
            result = call()
            best[key] = min(best[key], time.perf_counter() - start)
            if inspect is not None:
                inspect(key, result)
            del result
    return best
