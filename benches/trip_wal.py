#!/usr/bin/env python3
"""WAL bytes a trip batch writes on the PostgreSQL store (issue 11: the trip state write per batch
must not grow with the trip's length).

Starts a throw-away PostgreSQL server (Debian's server binaries, as the `postgres` user: run as
root) and one `seasonloc serve --database-url` on 127.0.0.1, builds a HOG map from the first
MAP_IMAGES summer frames of Nordland 64x32, opens one trip and posts BATCHES batches of BATCH
winter frames. For each batch it reads `pg_current_wal_lsn()` before and after (nothing else
writes to the database meanwhile) and prints the WAL bytes per batch at the start, middle and end
of the trip, so growth with the trip's length shows directly. Bounded: BATCHES x BATCH frames,
each request with a 120 s timeout.

usage: sudo python3 benches/trip_wal.py BINARY NORDLAND_DIR [MAP_IMAGES=2400] [BATCHES=60] [BATCH=10]
needs: Python 3 with `requests`; psql from the same PostgreSQL installation.
"""
import glob
import os
import pwd
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

import requests


def free_port():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    p = s.getsockname()[1]
    s.close()
    return p


def frames(data, season, lo, hi):
    names = sorted(n for n in os.listdir(os.path.join(data, season)) if n.endswith(".png"))[lo:hi]
    return [("image", (n, open(os.path.join(data, season, n), "rb").read(), "image/png")) for n in names]


def main():
    binary, data = sys.argv[1], sys.argv[2]
    map_images = int(sys.argv[3]) if len(sys.argv) > 3 else 2400
    batches = int(sys.argv[4]) if len(sys.argv) > 4 else 60
    batch = int(sys.argv[5]) if len(sys.argv) > 5 else 10
    pgbin = sorted(glob.glob("/usr/lib/postgresql/*/bin"))
    if not pgbin:
        raise SystemExit("no PostgreSQL server binaries (apt-get install postgresql)")
    pgbin = pgbin[-1]
    tmp = tempfile.mkdtemp()
    os.chmod(tmp, 0o755)
    pgdir = os.path.join(tmp, "pg")
    os.makedirs(pgdir)
    pw = pwd.getpwnam("postgres")
    os.chown(pgdir, pw.pw_uid, pw.pw_gid)
    pgport = free_port()

    def pg(*cmd):
        return subprocess.run(["runuser", "-u", "postgres", "--"] + list(cmd),
                              capture_output=True, text=True, timeout=120)

    r = pg(f"{pgbin}/initdb", "-D", pgdir, "-A", "trust", "-U", "postgres")
    if r.returncode:
        raise SystemExit("initdb failed: " + r.stderr[-300:])
    pg(f"{pgbin}/pg_ctl", "-D", pgdir, "-w", "-l", os.path.join(pgdir, "log"), "-o",
       f"-p {pgport} -k {pgdir} -c listen_addresses=127.0.0.1", "start")
    proc = None
    try:
        pg(f"{pgbin}/createdb", "-h", "127.0.0.1", "-p", str(pgport), "-U", "postgres", "seasonloc")

        def lsn_bytes():
            out = subprocess.run(
                [f"{pgbin}/psql", "-h", "127.0.0.1", "-p", str(pgport), "-U", "postgres", "-d",
                 "seasonloc", "-At", "-c", "SELECT pg_current_wal_lsn() - '0/0'::pg_lsn"],
                capture_output=True, text=True, timeout=60, check=True)
            return int(float(out.stdout.strip()))

        port = free_port()
        log = open(os.path.join(tmp, "serve.log"), "ab")
        url = f"postgres://postgres@127.0.0.1:{pgport}/seasonloc"
        proc = subprocess.Popen([binary, "serve", "--addr", f"127.0.0.1:{port}", "--database-url", url],
                                stdout=log, stderr=log, start_new_session=True)
        base = f"http://127.0.0.1:{port}"
        for _ in range(300):
            try:
                if requests.get(base + "/readyz", timeout=1).status_code == 200:
                    break
            except requests.RequestException:
                pass
            time.sleep(0.1)
        else:
            raise SystemExit("service did not become ready")
        mid = requests.post(base + "/v1/maps", json={"name": "wal", "descriptor": {"kind": "hog", "cell_size": 8}},
                            timeout=120).json()["id"]
        for lo in range(0, map_images, 400):
            requests.post(f"{base}/v1/maps/{mid}/images", files=frames(data, "summer", lo, min(lo + 400, map_images)),
                          timeout=120).raise_for_status()
        tid = requests.post(f"{base}/v1/maps/{mid}/trips", json={}, timeout=120).json()["id"]
        per_batch = []
        for b in range(batches):
            lo = (b * batch) % max(map_images - batch, 1)
            parts = frames(data, "winter", lo, lo + batch)
            before = lsn_bytes()
            requests.post(f"{base}/v1/trips/{tid}/frames", files=parts, timeout=120).raise_for_status()
            per_batch.append(lsn_bytes() - before)
        # psql's own statement writes no WAL (a read-only SELECT), so the difference is the batch's.
        third = max(batches // 3, 1)
        mean = lambda xs: sum(xs) / len(xs)
        print(f"map {map_images} images, batches of {batch} frames, {batches} batches")
        print(f"WAL bytes per batch: first third mean {mean(per_batch[:third]):.0f}, "
              f"middle third {mean(per_batch[third:2 * third]):.0f}, last third {mean(per_batch[2 * third:]):.0f}, "
              f"max {max(per_batch)}")
    finally:
        if proc is not None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait(timeout=30)
        pg(f"{pgbin}/pg_ctl", "-D", pgdir, "-w", "-m", "fast", "stop")
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
