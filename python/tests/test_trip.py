"""The online `Trip` (descriptors or images pushed in batches) and solving from several Python
threads at once."""

import threading

import numpy as np
import pytest

import seasonloc as sl
from conftest import planted


def test_trip_follows_a_route_from_descriptors_and_images(route):
    ref = sl.hog(route["reference"], cell_size=8)
    trip = sl.Trip(ref)
    qry = sl.hog(route["query"], cell_size=8, resize=(64, 32))
    estimates = []
    for k in range(0, 30, 10):
        batch = trip.push(qry[k:k + 10])
        assert [e.frame for e in batch] == list(range(k, k + 10))
        estimates += batch
    assert trip.frames == 30 and trip.status in ("localized", "lost", "relocalized")
    right = sum(e.ref is not None and abs(e.ref - (e.frame + 5)) <= 1 for e in estimates[10:])
    assert right >= 15, estimates
    assert all(e.status in ("localized", "uncertain", "off_map", "lost") for e in estimates)
    # The same frames as images, described by the trip's function.
    by_image = sl.Trip(ref, describe=lambda frames: sl.hog(frames, cell_size=8, resize=(64, 32)))
    again = by_image.push(route["query_pixels"][:10])
    assert again == estimates[:10]
    with pytest.raises(TypeError, match="describe"):
        sl.Trip(ref).push(route["query_pixels"][:2])
    with pytest.raises(ValueError, match="shape mismatch"):
        trip.push(np.ones((2, 7), np.float32))
    with pytest.raises(ValueError, match="lag"):
        sl.Trip(ref, lag=0)


def test_threads_solve_at_once_with_the_same_answers():
    mats = [planted(300, 600, s) for s in range(4)]
    alone = [sl.solve(m).to_dict() for m in mats]
    out = [None] * 4

    def work(i):
        out[i] = sl.solve(mats[i]).to_dict()

    ts = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert out == alone
