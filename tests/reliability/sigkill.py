#!/usr/bin/env python3
"""SIGKILL durability, cycle after cycle, on either store engine (issue 42's re-run; not part of
`cargo nextest`: it needs a built binary and, for PostgreSQL, a database).

Each cycle starts `seasonloc serve`, streams uploads to a map (precomputed descriptors, 4 rows a
batch) and frame batches to a trip on a HOG map (3 generated frames a batch) from two client
threads, and SIGKILLs the server after a random 0.2-1.5 s. Every other cycle sends each request
with an `Idempotency-Key`. After the restart it checks:
  - nothing acknowledged is lost: the map's image count and the trip's frame count are at least
    what was acknowledged, and at most that plus the one batch in flight at the kill;
  - nothing is torn: counts move by whole batches, the trip's estimates cover its frames;
  - a keyed request in flight at the kill, retried with its key, is applied exactly once (the
    retry is 200; it adds its batch only if the first attempt had not landed, and is answered
    `Idempotent-Replayed: true` if it had).
usage: sigkill.py BINARY [--cycles N] [--database-url URL]   (last line: the figure; exit 0 = all held)
"""
import json, os, random, shutil, signal, socket, struct, subprocess, sys, tempfile, threading, time, uuid, zlib
import urllib.request, urllib.error

argv = sys.argv[1:]
def opt(name, default):
    if name in argv:
        k = argv.index(name); v = argv[k + 1]; del argv[k:k + 2]; return v
    return default
CYCLES = int(opt("--cycles", "50"))
DB = opt("--database-url", "")
if len(argv) != 1:
    raise SystemExit(__doc__)
BIN = argv[0]
ROWS, FRAMES, DIM = 4, 3, 8


def png(seed, w=64, h=32):
    """A grayscale PNG of random blocks (a generated place)."""
    rnd = random.Random(seed)
    px = bytearray(w * h)
    for _ in range(6):
        x0, y0, bw, bh, v = rnd.randrange(w - 8), rnd.randrange(h - 8), rnd.randrange(4, 20), rnd.randrange(4, 12), rnd.randrange(256)
        for y in range(y0, min(h, y0 + bh)):
            px[y * w + x0:y * w + min(w, x0 + bw)] = bytes([v]) * (min(w, x0 + bw) - x0)
    raw = b"".join(b"\x00" + bytes(px[y * w:(y + 1) * w]) for y in range(h))
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)  # noqa: E731
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def request(base, method, path, body=None, ctype=None, headers=None, timeout=30):
    req = urllib.request.Request(base + path, data=body, method=method, headers=dict(headers or {}))
    if ctype:
        req.add_header("Content-Type", ctype)
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as e:
        return e.code, dict(e.headers), e.read()


def multipart(images):
    b = "sigkill" + uuid.uuid4().hex
    parts = [f"--{b}\r\nContent-Disposition: form-data; name=\"image\"; filename=\"{i}.png\"\r\nContent-Type: image/png\r\n\r\n".encode() + data + b"\r\n" for i, data in enumerate(images)]
    return b"".join(parts) + f"--{b}--\r\n".encode(), f"multipart/form-data; boundary={b}"


def free_port():
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]; s.close(); return p


class Server:
    def __init__(self, data):
        self.data, self.port, self.proc = data, free_port(), None
        self.base = f"http://127.0.0.1:{self.port}"

    def start(self):
        cmd = [BIN, "serve", "--addr", f"127.0.0.1:{self.port}", "--data-dir", self.data]
        if DB:
            cmd += ["--database-url", DB]
        self.log = open(os.path.join(os.path.dirname(self.data), "serve.log"), "ab")
        self.proc = subprocess.Popen(cmd, stdout=self.log, stderr=self.log)
        t0 = time.time()
        while time.time() - t0 < 30:
            try:
                if request(self.base, "GET", "/readyz", timeout=1)[0] == 200:
                    return
            except OSError:
                pass
            if self.proc.poll() is not None:
                raise SystemExit(f"the server exited at start ({self.proc.returncode}); see {self.log.name}")
            time.sleep(0.05)
        raise SystemExit("the server did not become ready in 30 s")

    def kill(self):
        self.proc.send_signal(signal.SIGKILL); self.proc.wait(); self.log.close()


def main():
    work = tempfile.mkdtemp(prefix="sigkill-")
    s = Server(os.path.join(work, "data"))
    s.start()
    st, _, b = request(s.base, "POST", "/v1/maps", json.dumps({"name": "vectors", "descriptor": {"kind": "precomputed", "dim": DIM}}).encode(), "application/json")
    assert st == 201, b
    vec = json.loads(b)["id"]
    st, _, b = request(s.base, "POST", "/v1/maps", json.dumps({"name": "hog", "descriptor": {"kind": "hog", "cell_size": 8}}).encode(), "application/json")
    assert st == 201, b
    hog = json.loads(b)["id"]
    body, ct = multipart([png(k) for k in range(24)])
    assert request(s.base, "POST", f"/v1/maps/{hog}/images", body, ct)[0] == 200
    st, _, b = request(s.base, "POST", f"/v1/maps/{hog}/trips", b"{}", "application/json")
    assert st == 201, b
    trip = json.loads(b)["id"]
    acked = {"images": 0, "frames": 0}
    failures, applied_keyed, counts = [], 0, {"requests": 0}

    def upload(kind, keyed, stop, pending):
        n = 0
        while not stop.is_set():
            key = uuid.uuid4().hex if keyed else None
            if kind == "images":
                rows = [[random.random() + 0.01 for _ in range(DIM)] for _ in range(ROWS)]
                body, ct, path = json.dumps({"descriptors": rows}).encode(), "application/json", f"/v1/maps/{vec}/descriptors"
            else:
                body, ct = multipart([png(1000 + (n * FRAMES + k) % 24) for k in range(FRAMES)])
                path = f"/v1/trips/{trip}/frames"
            pending[kind] = (path, body, ct, key)
            try:
                st, _, b = request(s.base, "POST", path, body, ct, {"Idempotency-Key": key} if key else None, timeout=10)
            except OSError:
                return  # the kill: this request is in flight
            pending[kind] = None
            counts["requests"] += 1
            if st == 200:
                acked[kind] += ROWS if kind == "images" else FRAMES
            else:
                failures.append(f"{kind}: {st} {b[:120]!r}")
            n += 1

    def stored():
        st, _, b = request(s.base, "GET", f"/v1/maps/{vec}")
        images = json.loads(b)["image_count"]
        st2, _, b2 = request(s.base, "GET", f"/v1/trips/{trip}")
        t = json.loads(b2)
        return images, t["frame_count"], len(t["estimates"])

    for cycle in range(CYCLES):
        keyed = cycle % 2 == 1
        stop, pending = threading.Event(), {"images": None, "frames": None}
        threads = [threading.Thread(target=upload, args=(k, keyed, stop, pending)) for k in ("images", "frames")]
        for t in threads:
            t.start()
        time.sleep(random.uniform(0.2, 1.5))
        s.kill(); stop.set()
        for t in threads:
            t.join(timeout=15)
        s.start()
        images, frames, estimates = stored()
        for kind, got, size in (("images", images, ROWS), ("frames", frames, FRAMES)):
            extra = got - acked[kind]
            inflight = pending[kind]
            if extra < 0:
                failures.append(f"cycle {cycle}: {kind} {got} < {acked[kind]} acknowledged (lost)")
            elif extra not in (0, size) or (extra == size and inflight is None):
                failures.append(f"cycle {cycle}: {kind} {got} = acknowledged {acked[kind]} + {extra} (torn or invented)")
            landed = extra == size
            if inflight and inflight[3]:
                path, body, ct, key = inflight
                st, h, b = request(s.base, "POST", path, body, ct, {"Idempotency-Key": key})
                replayed = h.get("Idempotent-Replayed") or h.get("idempotent-replayed")
                if st != 200:
                    failures.append(f"cycle {cycle}: retried keyed {kind}: {st} {b[:120]!r}")
                elif landed and replayed != "true":
                    failures.append(f"cycle {cycle}: a keyed {kind} batch that had landed was applied again")
                applied_keyed += 1
                acked[kind] += size
            elif landed:
                acked[kind] += size
        images, frames, estimates = stored()
        if (images, frames) != (acked["images"], acked["frames"]):
            failures.append(f"cycle {cycle}: after retries images {images} frames {frames}, want {acked['images']} {acked['frames']}")
        if estimates != frames:
            failures.append(f"cycle {cycle}: trip has {frames} frames but {estimates} estimates")
    s.kill()
    shutil.rmtree(work, ignore_errors=True)
    for f in failures[:20]:
        print("FAIL", f)
    engine = "postgres" if DB else "sled"
    print(f"sigkill ({engine}): {CYCLES} cycles, {counts['requests']} acknowledged requests, {acked['images']} rows, "
          f"{acked['frames']} frames, {applied_keyed} keyed retries after a kill; {len(failures)} failures")
    sys.exit(1 if failures else 0)


if __name__ == "__main__":
    main()
