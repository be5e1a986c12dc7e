"""``benchmarks/bench_imaging.py --only cluster``: its task-stream arithmetic, and (slow) a
tiny run whose table says what the cluster did."""

from __future__ import annotations

import pytest
from _bench_helpers import load_benchmark

bench = load_benchmark("bench_imaging")


def _task(key: str, *spans: tuple[float, float], action: str = "compute") -> dict:
    return {"key": key, "startstops": [{"action": action, "start": a, "stop": b}
                                       for a, b in spans]}


def test_task_span_counts_only_the_prefix_and_compute():
    stream = [_task("xstack-image-count-ab-0", (10.0, 10.5)),
              _task("xstack-image-count-ab-1", (10.2, 11.0)),
              _task("xstack-image-count-ab-1", (9.0, 9.9), action="transfer"),
              _task("xstack-image-grid-dirty-ab-0", (11.0, 20.0))]
    n, span, busy = bench._task_span(stream, "xstack-image-count")
    assert n == 2
    assert span == pytest.approx(1.0)  # 10.0 to 11.0; the transfer is not counted
    assert busy == pytest.approx(0.5 + 0.8)
    assert bench._task_span(stream, "nothing") == (0, 0.0, 0.0)


@pytest.mark.slow
def test_cluster_rows_report_same_bits_and_tasks(monkeypatch):
    """At 600 s integrations (56 times, 6 chunks of 10) cut into batches of ~1/3 of the
    visibilities: a planning task per chunk, more than one gridding task, the same bits."""
    from xstack.imaging import image as image_mod

    n_vis = 56 * 351 * 10 * 2
    monkeypatch.setattr(image_mod, "BATCH_VISIBILITIES", n_vis // 3)
    rows: list[str] = []
    bench.bench_cluster(rows, time_step=600.0, size=256, nsigma=5.0, epsilon=1e-4,
                        chunk_times=10)
    local, cluster = ([c.strip() for c in r.strip("|").split("|")] for r in rows)
    assert local[0] == "local" and cluster[0] == "cluster"
    assert cluster[2] == "6"
    assert int(cluster[3]) >= 2
    assert "6 tasks" in cluster[6]
    assert cluster[10:12] == ["yes", "yes"] and local[10:12] == ["yes", "yes"]
    assert cluster[8] == local[8]  # components
