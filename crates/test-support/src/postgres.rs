//! Throw-away PostgreSQL servers for the test suites (not used by the service itself).
//!
//! A [`TestServer`] is a real `postgres` from the Debian package (`/usr/lib/postgresql/*/bin`,
//! or the folder in `SEASONLOC_PG_BIN`), in a temporary folder, listening on a free port of
//! 127.0.0.1 only. Running as root (CI), the server runs as the unprivileged `postgres` user
//! (`runuser`), as PostgreSQL requires. The cluster is made once per machine and user by
//! `initdb` into a cached template folder (renamed into place atomically) and copied for each
//! server, so a server starts in well under a second.
//!
//! Each server has a watchdog: a shell that holds the read end of a pipe from the test
//! process; when the test process exits, however it exits, the pipe closes and the watchdog
//! stops the server and deletes its folder. So a server shared by a whole test binary
//! ([`shared`]) needs no teardown.
//!
//! [`available`] says whether tests can run here: `Err(reason)` when the binaries are absent,
//! which tests turn into a skip, except under `CI=true` where they must fail
//! ([`require`]).

use std::io::Write;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Mutex, OnceLock};
use std::time::{Duration, Instant};

/// The folder of the PostgreSQL server binaries, or why there is none.
pub fn available() -> Result<PathBuf, String> {
    if let Some(dir) = std::env::var_os("SEASONLOC_PG_BIN") {
        let dir = PathBuf::from(dir);
        return if dir.join("pg_ctl").exists() {
            Ok(dir)
        } else {
            Err(format!("SEASONLOC_PG_BIN={} has no pg_ctl", dir.display()))
        };
    }
    let mut found: Vec<PathBuf> = std::fs::read_dir("/usr/lib/postgresql")
        .map_err(|_| {
            "no PostgreSQL server binaries in /usr/lib/postgresql (apt-get install postgresql)"
                .to_string()
        })?
        .filter_map(|e| e.ok().map(|e| e.path().join("bin")))
        .filter(|bin| bin.join("initdb").exists() && bin.join("pg_ctl").exists())
        .collect();
    found.sort_by_key(|p| {
        p.parent()
            .and_then(|v| v.file_name())
            .and_then(|v| v.to_str())
            .and_then(|v| v.parse::<u32>().ok())
            .unwrap_or(0)
    });
    found.pop().ok_or_else(|| {
        "no PostgreSQL server binaries in /usr/lib/postgresql/*/bin (apt-get install postgresql)"
            .to_string()
    })
}

/// The binaries' folder; `None` (after printing why) when the test should be skipped. Panics
/// when they are absent and `CI=true`: CI must never pass by skipping.
pub fn require(test: &str) -> Option<PathBuf> {
    match available() {
        Ok(bin) => Some(bin),
        Err(why) if std::env::var("CI").is_ok_and(|v| v == "true") => {
            panic!("{test}: PostgreSQL is required when CI=true: {why}")
        }
        Err(why) => {
            eprintln!("SKIPPED {test}: {why}");
            None
        }
    }
}

/// Whether this process runs as root (then the server runs as `postgres`).
/// Whether this process runs as root.
pub fn is_root() -> bool {
    static ROOT: OnceLock<bool> = OnceLock::new();
    *ROOT.get_or_init(|| {
        Command::new("id")
            .arg("-u")
            .output()
            .is_ok_and(|o| o.stdout.trim_ascii() == b"0")
    })
}

/// A command run as the server's user.
fn as_server_user(program: &Path) -> Command {
    if is_root() {
        let mut c = Command::new("runuser");
        c.args(["-u", "postgres", "--"]).arg(program);
        c
    } else {
        Command::new(program)
    }
}

fn run(mut cmd: Command, what: &str) -> Result<(), String> {
    let out = cmd
        .stdin(Stdio::null())
        .output()
        .map_err(|e| format!("{what}: {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "{what} failed ({}): {}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ))
    }
}

/// Makes `path` owned by the server's user (when root).
fn hand_over(path: &Path) -> Result<(), String> {
    if is_root() {
        let mut c = Command::new("chown");
        c.args(["-R", "postgres:"]).arg(path);
        run(c, "chown")?;
    }
    Ok(())
}

/// The cached `initdb` cluster, made once per machine: `initdb` into a folder of this process,
/// then renamed into place atomically (a concurrent first run by another process makes its own
/// and the loser's is dropped), so no lock is needed and a half-made cluster is never used.
fn template(bin: &Path) -> Result<PathBuf, String> {
    let version = bin
        .parent()
        .and_then(|v| v.file_name())
        .map_or_else(|| "pg".into(), |v| v.to_string_lossy().into_owned());
    let root = std::env::temp_dir().join(format!("seasonloc-pg-template-{version}"));
    let cluster = root.join("cluster");
    if cluster.join("PG_VERSION").exists() {
        return Ok(cluster);
    }
    std::fs::create_dir_all(&root).map_err(|e| format!("{}: {e}", root.display()))?;
    // The server's user must reach the folder.
    let mut chmod = Command::new("chmod");
    chmod.arg("755").arg(&root);
    run(chmod, "chmod")?;
    let mine = root.join(format!("making-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&mine);
    std::fs::create_dir_all(&mine).map_err(|e| format!("{}: {e}", mine.display()))?;
    hand_over(&mine)?;
    let mut init = as_server_user(&bin.join("initdb"));
    init.arg("-D")
        .arg(&mine)
        .args(["-A", "trust", "-U", "postgres", "--no-sync", "-E", "UTF8"]);
    run(init, "initdb")?;
    if std::fs::rename(&mine, &cluster).is_err() {
        // Another process installed its template first.
        let _ = std::fs::remove_dir_all(&mine);
    }
    if cluster.join("PG_VERSION").exists() {
        Ok(cluster)
    } else {
        Err(format!("no template cluster at {}", cluster.display()))
    }
}

fn free_port() -> Result<u16, String> {
    let l = TcpListener::bind("127.0.0.1:0").map_err(|e| format!("no free port: {e}"))?;
    l.local_addr()
        .map(|a| a.port())
        .map_err(|e| format!("no free port: {e}"))
}

/// A PostgreSQL server of the tests. Dropping it stops it and deletes its folder.
pub struct TestServer {
    bin: PathBuf,
    dir: PathBuf,
    port: u16,
    watchdog: Mutex<Option<(Child, ChildStdin)>>,
    databases: AtomicUsize,
    /// Extra `postgres` options (`-c ssl=on ...` for [`TestServer::start_tls`]).
    options: String,
}

impl TestServer {
    /// Copies the template cluster to a new folder and starts a server on a free port.
    pub fn start(bin: &Path) -> Result<TestServer, String> {
        TestServer::start_with(bin, None)
    }

    /// [`TestServer::start`] with TLS on (`ssl=on`, this PEM certificate chain and key) and
    /// TCP connections accepted over TLS only (`hostssl` in `pg_hba.conf`): a client that
    /// does not encrypt is refused.
    pub fn start_tls(bin: &Path, cert_pem: &str, key_pem: &str) -> Result<TestServer, String> {
        TestServer::start_with(bin, Some((cert_pem, key_pem)))
    }

    fn start_with(bin: &Path, tls: Option<(&str, &str)>) -> Result<TestServer, String> {
        let cluster = template(bin)?;
        let dir = std::env::temp_dir().join(format!(
            "seasonloc-pg-{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        ));
        let _ = std::fs::remove_dir_all(&dir);
        let mut cp = Command::new("cp");
        cp.arg("-a").arg(&cluster).arg(&dir);
        run(cp, "copying the template cluster")?;
        let mut chmod = Command::new("chmod");
        chmod.arg("700").arg(&dir);
        run(chmod, "chmod")?;
        let mut options = String::new();
        if let Some((cert, key)) = tls {
            let write = |name: &str, text: &str| {
                let path = dir.join(name);
                std::fs::write(&path, text).map_err(|e| format!("{}: {e}", path.display()))
            };
            write("server.crt", cert)?;
            write("server.key", key)?;
            let mut chmod = Command::new("chmod");
            chmod.arg("600").arg(dir.join("server.key"));
            run(chmod, "chmod")?;
            hand_over(&dir)?;
            let hba = dir.join("pg_hba.conf");
            let text =
                std::fs::read_to_string(&hba).map_err(|e| format!("{}: {e}", hba.display()))?;
            let text: String = text
                .lines()
                .map(|l| match l.strip_prefix("host ") {
                    Some(rest) => format!("hostssl {rest}\n"),
                    None => format!("{l}\n"),
                })
                .collect();
            write("pg_hba.conf", &text)?;
            hand_over(&dir)?;
            options = " -c ssl=on -c ssl_cert_file=server.crt -c ssl_key_file=server.key".into();
        }
        // The watchdog: stops the server and deletes the folder when our end of its stdin
        // closes (this process exited or dropped the server).
        let script = format!(
            "read _; {} -D '{d}' -m immediate -w stop >/dev/null 2>&1; rm -rf '{d}'",
            shell_command(&bin.join("pg_ctl")),
            d = dir.display()
        );
        let mut child = Command::new("sh")
            .args(["-c", &script])
            .stdin(Stdio::piped())
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .map_err(|e| format!("watchdog: {e}"))?;
        let stdin = child
            .stdin
            .take()
            .ok_or_else(|| "watchdog without stdin".to_string())?;
        let server = TestServer {
            bin: bin.to_path_buf(),
            dir,
            port: free_port()?,
            watchdog: Mutex::new(Some((child, stdin))),
            databases: AtomicUsize::new(0),
            options,
        };
        server.resume()?;
        Ok(server)
    }

    /// The port on 127.0.0.1.
    pub fn port(&self) -> u16 {
        self.port
    }

    /// Starts the (stopped) server again, on the same port and data.
    pub fn resume(&self) -> Result<(), String> {
        let mut start = as_server_user(&self.bin.join("pg_ctl"));
        start
            .arg("-D")
            .arg(&self.dir)
            .arg("-l")
            .arg(self.dir.join("log"))
            .arg("-w")
            .arg("-o")
            .arg(format!(
                "-p {} -k {} -c listen_addresses=127.0.0.1 -c fsync=off \
                 -c full_page_writes=off -c shared_buffers=32MB -c max_connections=200{}",
                self.port,
                self.dir.display(),
                self.options
            ))
            .arg("start");
        run(start, "pg_ctl start").map_err(|e| {
            let log = std::fs::read_to_string(self.dir.join("log")).unwrap_or_default();
            format!("{e}\n{log}")
        })
    }

    /// Stops the server (`fast`: open connections are closed), keeping its data.
    pub fn pause(&self) -> Result<(), String> {
        let mut stop = as_server_user(&self.bin.join("pg_ctl"));
        stop.arg("-D")
            .arg(&self.dir)
            .args(["-m", "fast", "-w", "stop"]);
        run(stop, "pg_ctl stop")
    }

    /// The server's processes: the postmaster of this server's folder and its children.
    fn pids(&self) -> Vec<u32> {
        let Some(master) = std::fs::read_to_string(self.dir.join("postmaster.pid"))
            .ok()
            .and_then(|t| t.lines().next().and_then(|l| l.trim().parse::<u32>().ok()))
        else {
            return Vec::new();
        };
        let mut out = vec![master];
        for e in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
            let Some(pid) = e.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else {
                continue;
            };
            let stat = std::fs::read_to_string(e.path().join("stat")).unwrap_or_default();
            let ppid = stat
                .rsplit_once(')')
                .and_then(|(_, rest)| rest.split_whitespace().nth(1))
                .and_then(|p| p.parse::<u32>().ok());
            if ppid == Some(master) {
                out.push(pid);
            }
        }
        out
    }

    fn signal(&self, sig: &str) -> Result<(), String> {
        let pids = self.pids();
        if pids.is_empty() {
            return Err("no server process found".into());
        }
        let mut kill = Command::new("kill");
        kill.arg(sig).args(pids.iter().map(u32::to_string));
        run(kill, "kill")
    }

    /// Hangs the server: every one of its processes stopped (SIGSTOP), its sockets open, so
    /// the kernel still accepts connections and acknowledges data that nobody answers.
    pub fn freeze(&self) -> Result<(), String> {
        // Twice: a child forked while the first signal went out is stopped by the second.
        self.signal("-STOP")?;
        std::thread::sleep(Duration::from_millis(50));
        self.signal("-STOP")
    }

    /// Lets a [`TestServer::freeze`]d server run again.
    pub fn thaw(&self) -> Result<(), String> {
        self.signal("-CONT")
    }

    /// Creates a new empty database and returns its URL.
    pub fn database(&self) -> Result<String, String> {
        let name = format!("t{}", self.databases.fetch_add(1, Ordering::Relaxed));
        let mut create = Command::new(self.bin.join("createdb"));
        create
            .args(["-h", "127.0.0.1", "-U", "postgres", "-p"])
            .arg(self.port.to_string())
            .arg(&name);
        run(create, "createdb")?;
        Ok(self.url(&name))
    }

    /// The URL of database `name`.
    pub fn url(&self, name: &str) -> String {
        format!("postgres://postgres@127.0.0.1:{}/{name}", self.port)
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        let taken = self
            .watchdog
            .get_mut()
            .map_or_else(|p| p.into_inner().take(), Option::take);
        if let Some((mut child, mut stdin)) = taken {
            let _ = stdin.write_all(b"\n");
            drop(stdin);
            let deadline = Instant::now() + Duration::from_secs(30);
            while Instant::now() < deadline {
                if let Ok(Some(_)) = child.try_wait() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        }
    }
}

/// `program` as the server's user, quoted for `sh`.
fn shell_command(program: &Path) -> String {
    let p = format!("'{}'", program.display());
    if is_root() {
        format!("runuser -u postgres -- {p}")
    } else {
        p
    }
}

static NEXT: AtomicUsize = AtomicUsize::new(0);

/// The server shared by every test of this process (started on first use); `Err` when it
/// cannot start. Stopped by its watchdog when the process exits.
pub fn shared() -> Result<&'static TestServer, String> {
    static SERVER: OnceLock<Result<TestServer, String>> = OnceLock::new();
    SERVER
        .get_or_init(|| available().and_then(|bin| TestServer::start(&bin)))
        .as_ref()
        .map_err(Clone::clone)
}

/// A new database on the [`shared`] server, for `test`; `None` (after printing why) when
/// PostgreSQL is absent and the test should be skipped (a panic under `CI=true`).
pub fn database(test: &str) -> Option<String> {
    require(test)?;
    match shared().and_then(TestServer::database) {
        Ok(url) => Some(url),
        Err(e) => panic!("{test}: cannot start the test PostgreSQL server: {e}"),
    }
}
