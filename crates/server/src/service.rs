//! `seasonloc serve`: start-up (logging, store, CPU pool, listener), the one log line with the
//! bound address, and graceful shutdown on SIGTERM/Ctrl-C.
//!
//! With `--api-keys`, SIGHUP re-reads the key file (rotation without restart); a file that does
//! not load keeps the previous keys and logs why.
//!
//! Connections are served by hyper's HTTP/1.1 server directly (not `axum::serve`) so that the
//! header read timeout applies: a client gets `header_read_timeout` to send a request's header,
//! then it is disconnected (slowloris); a stalled or trickling body is cut off by the router's
//! body read timeout and body deadline (408). At most `--max-connections` connections are
//! served at once ([`crate::connections`]): at the cap, the one that has waited longest for a
//! request header makes room.
//!
//! Shutdown stops accepting connections, lets in-flight requests finish for at most
//! `shutdown_timeout`, then flushes the store. Every acknowledged write was already flushed, so
//! the final flush only covers the store's own bookkeeping.

use std::future::Future;
use std::sync::Arc;

use std::sync::atomic::Ordering;

use anyhow::Context;
use tokio::net::TcpListener;
use tower::ServiceExt;

use crate::api::{self, AppState};
use crate::config::{descriptor_room, ServeArgs, Settings};
use crate::connections::ConnectionCap;
use seasonloc_app::store::Store;
use seasonloc_app::{App, AppConfig};
use seasonloc_store::{PgOptions, PgStore, SledOptions, SledStore};

/// Entry point of `seasonloc serve`: validates `args`, logs to stderr (`RUST_LOG`, default
/// `info`, in `--log-format`), and serves until SIGTERM or Ctrl-C.
pub fn run_serve(args: ServeArgs) -> anyhow::Result<()> {
    let telemetry = crate::telemetry::init(args.log_format, args.otlp_endpoint.as_deref())?;
    let settings = args.validate()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("seasonloc-http")
        .build()
        .context("starting the async runtime")?;
    let served = runtime.block_on(async move {
        let listener = TcpListener::bind(settings.addr)
            .await
            .with_context(|| format!("cannot listen on {}", settings.addr))?;
        serve(settings, listener, shutdown_signal()).await
    });
    telemetry.shutdown();
    served
}

/// The use-case layer's settings from the service's.
pub fn app_config(settings: &Settings) -> AppConfig {
    AppConfig {
        worker_threads: settings.worker_threads,
        max_image_pixels: settings.max_image_pixels,
        max_batch_pixels: settings.max_batch_pixels,
        default_cnn_model: settings.default_cnn_model.clone(),
        max_descriptor_len: settings.max_descriptor_len,
        models: seasonloc_app::ModelPolicy {
            dir: settings.model_dir.clone(),
            max_bytes: settings.max_model_bytes,
        },
    }
}

/// Runs `f` (opening the embedded store) with the panic hook replaced by one log line: the
/// store turns a panic of its engine on a damaged file into `StoreError::Damaged`, and the
/// operator should read that error, not a panic message and a backtrace.
fn quiet_panics<T>(f: impl FnOnce() -> T) -> T {
    let previous = std::panic::take_hook();
    std::panic::set_hook(Box::new(|info| {
        let at = info
            .location()
            .map(|l| format!("{}:{}", l.file(), l.line()))
            .unwrap_or_default();
        tracing::error!(at, "the storage engine stopped on bytes it could not read");
    }));
    let out = f();
    let _ = std::panic::take_hook();
    std::panic::set_hook(previous);
    out
}

/// Serves on `listener` until `shutdown` completes, then drains and flushes the store.
pub async fn serve(
    settings: Settings,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    // The key file first: a deployment that forgot to mount it fails before touching the store.
    let auth = AppState::load_auth(&settings)?;
    let store: Arc<dyn Store> = match &settings.database_url {
        Some(url) => {
            let options = PgOptions {
                statement_timeout: settings.database_statement_timeout,
                tcp_user_timeout: settings.database_tcp_user_timeout,
            };
            Arc::new(PgStore::connect_with(&url.0, &options).await?)
        }
        None => {
            let dir = settings.data_dir.clone();
            let options = SledOptions {
                cache_bytes: settings.store_cache_bytes,
            };
            Arc::new(
                tokio::task::spawn_blocking(move || -> anyhow::Result<SledStore> {
                    std::fs::create_dir_all(&dir).with_context(|| {
                        format!("cannot create the data folder {}", dir.display())
                    })?;
                    Ok(quiet_panics(|| SledStore::open_with(&dir, options))?)
                })
                .await??,
            )
        }
    };
    let drain = settings.shutdown_timeout;
    let metrics = Arc::new(api::metrics::Metrics::default());
    let store: Arc<dyn Store> = Arc::new(seasonloc_app::timed_store::TimedStore::new(
        store,
        Arc::clone(&metrics) as Arc<dyn seasonloc_app::timed_store::StoreObserver>,
    ));
    let use_cases = Arc::new(App::new(store, app_config(&settings))?);
    let state = AppState::with_metrics(Arc::clone(&use_cases), settings, auth, metrics)?;
    match &state.auth {
        Some(auth) => {
            tracing::info!(
                keys = auth.ring().len(),
                file = %auth.path().display(),
                "access control on: API keys loaded (SIGHUP re-reads the file)"
            );
            reload_keys_on_sighup(Arc::clone(auth));
        }
        None => tracing::warn!("access control off: no --api-keys, every request is let through"),
    }
    let header_timeout = state.settings.header_read_timeout;
    let room = descriptor_room();
    let max_connections = state.settings.max_connections.min(room);
    if max_connections < state.settings.max_connections {
        tracing::warn!(
            "--max-connections {} is more than the descriptor limit leaves room for; serving at \
             most {max_connections} connections (raise the limit, e.g. `ulimit -n`)",
            state.settings.max_connections
        );
    }
    let cap = std::sync::Arc::new(ConnectionCap::new(max_connections));
    let app = api::app(state);
    let addr = listener.local_addr()?;
    tracing::info!(
        store = %use_cases.store_location(),
        max_connections,
        "seasonloc serve listening on http://{addr}"
    );

    let http = http1_builder(header_timeout);
    let graceful = hyper_util::server::graceful::GracefulShutdown::new();
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let (stream, _) = tokio::select! {
            () = &mut shutdown => break,
            accepted = listener.accept() => match accepted {
                Ok(conn) => conn,
                Err(e) => {
                    // Out of file descriptors and the like: wait instead of spinning.
                    tracing::error!("accepting a connection: {e}");
                    tokio::time::sleep(std::time::Duration::from_millis(200)).await;
                    continue;
                }
            },
        };
        let Some((slot, displaced)) = cap.admit() else {
            // Every connection is busy with a request: this one is closed at once.
            tracing::debug!(
                max = cap.max(),
                "connection refused: every connection under --max-connections is busy"
            );
            drop(stream);
            continue;
        };
        // Small answers go out at once instead of waiting for Nagle's algorithm.
        let _ = stream.set_nodelay(true);
        // The connection waits for a header until a request arrives, and again once its
        // response has been sent (the body dropped): only then may it make room for another.
        let (started, sent) = (slot.waiting(), slot.waiting());
        let service = app
            .clone()
            .map_request(move |req: axum::http::Request<hyper::body::Incoming>| {
                started.store(false, Ordering::Relaxed);
                req
            })
            .map_response(move |response: axum::response::Response| {
                let sent = std::sync::Arc::clone(&sent);
                response.map(|body| {
                    axum::body::Body::new(api::body::OnDrop::new(body, move || {
                        sent.store(true, Ordering::Relaxed);
                    }))
                })
            });
        let service = hyper_util::service::TowerToHyperService::new(service);
        let conn = http.serve_connection(hyper_util::rt::TokioIo::new(stream), service);
        let conn = graceful.watch(conn);
        tokio::spawn(async move {
            tokio::select! {
                // Clients that hang up, send garbage or are too slow with their header end here.
                done = conn => if let Err(e) = done {
                    tracing::debug!("connection closed: {e}");
                },
                () = slot.evicted() => {
                    tracing::debug!("connection closed to make room under --max-connections");
                }
            }
            drop(slot);
        });
        // The connection that made room is closed before the next accept, so descriptors stay
        // within the cap however fast connections arrive (bounded, in case its task is slow).
        if let Some(displaced) = displaced {
            let _ = tokio::time::timeout(std::time::Duration::from_millis(100), displaced.closed())
                .await;
        }
        // Let the new connection read its request before the next accept: a burst of accepts
        // (up to the runtime's budget) could otherwise make room with connections whose
        // complete header is already waiting to be read.
        tokio::task::yield_now().await;
    }
    tracing::info!("shutdown requested: draining in-flight requests");
    tokio::select! {
        () = graceful.shutdown() => {}
        () = tokio::time::sleep(drain) => {
            tracing::warn!("drain timeout elapsed; exiting with requests in flight");
        }
    }
    use_cases.flush().await?;
    tracing::info!("store flushed; stopped");
    Ok(())
}

/// HTTP/1.1 connections whose request header must arrive within `header_timeout` (from the
/// connection's start, or from the end of the previous response on a kept-alive connection);
/// a client that is slower (half a header, then nothing) is disconnected.
fn http1_builder(header_timeout: std::time::Duration) -> hyper::server::conn::http1::Builder {
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(hyper_util::rt::TokioTimer::new())
        .header_read_timeout(header_timeout);
    http
}

/// Spawns the task that re-reads the key file on each SIGHUP.
fn reload_keys_on_sighup(auth: Arc<api::auth::Auth>) {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let mut hangups = match signal(SignalKind::hangup()) {
            Ok(s) => s,
            Err(e) => {
                tracing::error!("cannot listen for SIGHUP (API keys will not be reloaded): {e}");
                return;
            }
        };
        tokio::spawn(async move {
            while hangups.recv().await.is_some() {
                let a = Arc::clone(&auth);
                match tokio::task::spawn_blocking(move || a.reload()).await {
                    Ok(Ok(n)) => tracing::info!(keys = n, "SIGHUP: API keys reloaded"),
                    Ok(Err(e)) => tracing::error!("SIGHUP: keeping the previous API keys: {e}"),
                    Err(e) => tracing::error!("SIGHUP: keeping the previous API keys: {e}"),
                }
            }
        });
    }
    #[cfg(not(unix))]
    let _ = auth;
}

/// Completes on Ctrl-C or (on Unix) SIGTERM.
pub async fn shutdown_signal() {
    let ctrl_c = async {
        if let Err(e) = tokio::signal::ctrl_c().await {
            tracing::error!("cannot listen for Ctrl-C: {e}");
            std::future::pending::<()>().await;
        }
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(e) => {
                tracing::error!("cannot listen for SIGTERM: {e}");
                std::future::pending::<()>().await;
            }
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        () = ctrl_c => {},
        () = terminate => {},
    }
}
