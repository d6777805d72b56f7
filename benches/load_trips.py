#!/usr/bin/env python3
"""Fleet load on one or more seasonloc replicas (BENCHMARKS.md, "Scale-out"; docs/scaling.md).

Builds a HOG map of the 2,400 Nordland summer frames (uploads through the replicas in turn),
runs LOCALIZE requests of 100 winter frames, then VEHICLES trips that each post BATCHES batches
of 10 winter frames, every vehicle sending its batches to the replicas in turn (so a trip's
batches alternate between replicas). Bounded: at most VEHICLES x BATCHES batches and
MAX_SECONDS seconds. Standard library only.

usage: load_trips.py URL[,URL...] NORDLAND_DIR [--vehicles 64] [--batches 8] [--max-seconds 300]
                     [--localize 8] [--psql 'psql -h 127.0.0.1 -p PORT -U postgres -d DB']
Prints one JSON object: throughput and latency percentiles per operation, and with --psql the
database's busy time (pg_stat_database.active_time) as a share of the summed request time.
"""
import argparse, http.client, json, os, subprocess, threading, time, urllib.parse, uuid

BOUNDARY = "seasonlocloadboundary"


def multipart(paths):
    out = []
    for p in paths:
        name = os.path.basename(p)
        out.append(f"--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"image\"; "
                   f"filename=\"{name}\"\r\nContent-Type: image/png\r\n\r\n".encode())
        with open(p, "rb") as f:
            out.append(f.read())
        out.append(b"\r\n")
    out.append(f"--{BOUNDARY}--\r\n".encode())
    return b"".join(out)


def request(base, method, path, body=None, content_type=None, headers=None):
    u = urllib.parse.urlparse(base)
    c = http.client.HTTPConnection(u.hostname, u.port, timeout=120)
    h = dict(headers or {})
    if content_type:
        h["Content-Type"] = content_type
    t = time.perf_counter()
    c.request(method, path, body=body, headers=h)
    r = c.getresponse()
    data = r.read()
    dt = time.perf_counter() - t
    c.close()
    if r.status >= 300:
        raise RuntimeError(f"{method} {path}: {r.status} {data[:200]!r}")
    return json.loads(data) if data else None, dt


def pct(xs, q):
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))] if xs else None


def summary(name, lat, items, wall):
    return {"op": name, "requests": len(lat), "items_per_s": round(items / wall, 1) if wall else None,
            "p50_ms": round(1000 * pct(lat, 0.5), 1) if lat else None,
            "p99_ms": round(1000 * pct(lat, 0.99), 1) if lat else None, "wall_s": round(wall, 2)}


def sql(psql, query):
    return subprocess.run(psql.split() + ["-At", "-c", query],
                          capture_output=True, text=True, check=True).stdout.strip()


def db_active_ms(psql):
    if not psql:
        return None
    return float(sql(psql, "SELECT sum(active_time) FROM pg_stat_database") or 0)


def wal_bytes(psql):
    """The server's WAL position in bytes (what every write since costs in log volume)."""
    if not psql:
        return None
    return int(sql(psql, "SELECT pg_current_wal_lsn() - '0/0'::pg_lsn") or 0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("targets")
    ap.add_argument("data")
    ap.add_argument("--vehicles", type=int, default=64)
    ap.add_argument("--batches", type=int, default=8)
    ap.add_argument("--max-seconds", type=float, default=300)
    ap.add_argument("--localize", type=int, default=8)
    ap.add_argument("--psql", default="")
    a = ap.parse_args()
    targets = a.targets.split(",")
    summer = sorted(os.path.join(a.data, "summer", n) for n in os.listdir(os.path.join(a.data, "summer")))
    winter = sorted(os.path.join(a.data, "winter", n) for n in os.listdir(os.path.join(a.data, "winter")))
    ct = f"multipart/form-data; boundary={BOUNDARY}"
    result = {"replicas": len(targets), "vehicles": a.vehicles, "batch_frames": 10}

    m, _ = request(targets[0], "POST", "/v1/maps", json.dumps({"name": "load", "descriptor": {"kind": "hog", "cell_size": 8}}).encode(), "application/json")
    mid = m["id"]
    lat, t0 = [], time.perf_counter()
    for k, lo in enumerate(range(0, len(summer), 200)):
        _, dt = request(targets[k % len(targets)], "POST", f"/v1/maps/{mid}/images", multipart(summer[lo:lo + 200]), ct)
        lat.append(dt)
    result["upload"] = summary("upload (200 images)", lat, len(summer), time.perf_counter() - t0)

    lat, t0 = [], time.perf_counter()
    for k in range(a.localize):
        lo = (k * 277) % (len(winter) - 100)
        _, dt = request(targets[k % len(targets)], "POST", f"/v1/maps/{mid}/localize", multipart(winter[lo:lo + 100]), ct)
        lat.append(dt)
    result["localize"] = summary("localize (100 queries)", lat, 100 * a.localize, time.perf_counter() - t0)

    trips = []
    for v in range(a.vehicles):
        t, _ = request(targets[v % len(targets)], "POST", f"/v1/maps/{mid}/trips", b"{}", "application/json")
        trips.append(t["id"])
    bodies = {}
    lat, lock, errors = [], threading.Lock(), []
    deadline = time.perf_counter() + a.max_seconds
    active0 = db_active_ms(a.psql)
    wal0 = wal_bytes(a.psql)

    def vehicle(v):
        start = (v * 37) % (len(winter) - 10 * a.batches)
        for k in range(a.batches):
            if time.perf_counter() > deadline:
                return
            lo = start + 10 * k
            body = bodies.get(lo) or multipart(winter[lo:lo + 10])
            bodies[lo] = body
            try:
                _, dt = request(targets[(v + k) % len(targets)], "POST", f"/v1/trips/{trips[v]}/frames", body, ct,
                                {"Idempotency-Key": str(uuid.uuid4())})
                with lock:
                    lat.append(dt)
            except Exception as e:  # noqa: BLE001 (reported, not fatal)
                with lock:
                    errors.append(str(e)[:200])

    t0 = time.perf_counter()
    threads = [threading.Thread(target=vehicle, args=(v,)) for v in range(a.vehicles)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    result["frames"] = summary("trip batch (10 frames)", lat, 10 * len(lat), wall)
    result["frames"]["errors"] = len(errors)
    if errors:
        result["frames"]["first_error"] = errors[0]
    if a.psql:
        busy = db_active_ms(a.psql) - active0
        result["frames"]["db_active_s"] = round(busy / 1000, 2)
        result["frames"]["db_share_of_request_time"] = round(busy / 1000 / sum(lat), 3) if lat else None
        # What one batch writes: the trip's state row (whole, today) and the WAL it causes.
        result["frames"]["wal_bytes_per_batch"] = round((wal_bytes(a.psql) - wal0) / len(lat)) if lat else None
        result["frames"]["state_bytes"] = int(float(sql(a.psql, "SELECT avg(octet_length(state)) FROM trips") or 0))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
