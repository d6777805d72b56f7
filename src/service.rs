//! `seasonloc serve`: start-up (logging, store, CPU pool, listener), the one log line with the
//! bound address, and graceful shutdown on SIGTERM/Ctrl-C.
//!
//! With `--api-keys`, SIGHUP re-reads the key file (rotation without restart); a file that does
//! not load keeps the previous keys and logs why.
//!
//! Shutdown stops accepting connections, lets in-flight requests finish for at most
//! `shutdown_timeout`, then flushes the store. Every acknowledged write was already flushed, so
//! the final flush only covers the store's own bookkeeping.

use std::future::Future;
use std::sync::Arc;

use anyhow::Context;
use tokio::net::TcpListener;

use crate::api::{self, AppState};
use crate::app::{App, AppConfig};
use crate::config::{ServeArgs, Settings};
use crate::store::{PgStore, SledStore, Store};

/// Entry point of `seasonloc serve`: validates `args`, logs to stderr (`RUST_LOG`, default
/// `info`), and serves until SIGTERM or Ctrl-C.
pub fn run_serve(args: ServeArgs) -> anyhow::Result<()> {
    init_tracing();
    let settings = args.validate()?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("seasonloc-http")
        .build()
        .context("starting the async runtime")?;
    runtime.block_on(async move {
        let listener = TcpListener::bind(settings.addr)
            .await
            .with_context(|| format!("cannot listen on {}", settings.addr))?;
        serve(settings, listener, shutdown_signal()).await
    })
}

/// Installs the stderr logger unless one is installed already.
pub fn init_tracing() {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .try_init();
}

/// Serves on `listener` until `shutdown` completes, then drains and flushes the store.
pub async fn serve(
    settings: Settings,
    listener: TcpListener,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> anyhow::Result<()> {
    let store: Arc<dyn Store> = match &settings.database_url {
        Some(url) => Arc::new(PgStore::connect(&url.0).await?),
        None => {
            let dir = settings.data_dir.clone();
            Arc::new(
                tokio::task::spawn_blocking(move || -> anyhow::Result<SledStore> {
                    std::fs::create_dir_all(&dir).with_context(|| {
                        format!("cannot create the data folder {}", dir.display())
                    })?;
                    Ok(SledStore::open(&dir)?)
                })
                .await??,
            )
        }
    };
    let drain = settings.shutdown_timeout;
    let use_cases = Arc::new(App::new(
        store,
        AppConfig {
            worker_threads: settings.worker_threads,
            max_image_pixels: settings.max_image_pixels,
            default_cnn_model: settings.default_cnn_model.clone(),
            max_descriptor_len: settings.max_descriptor_len,
            models: crate::app::ModelPolicy {
                dir: settings.model_dir.clone(),
                max_bytes: settings.max_model_bytes,
            },
        },
    )?);
    let state = AppState::new(Arc::clone(&use_cases), settings)?;
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
    let app = api::app(state);
    let addr = listener.local_addr()?;
    tracing::info!(store = %use_cases.store_location(), "seasonloc serve listening on http://{addr}");

    let (stop_tx, mut stop_rx) = tokio::sync::watch::channel(false);
    let signal = async move {
        shutdown.await;
        tracing::info!("shutdown requested: draining in-flight requests");
        let _ = stop_tx.send(true);
    };
    let server = axum::serve(listener, app).with_graceful_shutdown(signal);
    let deadline = async move {
        if stop_rx.wait_for(|stop| *stop).await.is_err() {
            std::future::pending::<()>().await;
        }
        tokio::time::sleep(drain).await;
    };
    tokio::select! {
        result = server => result.context("serving HTTP")?,
        () = deadline => tracing::warn!("drain timeout elapsed; exiting with requests in flight"),
    }
    use_cases.flush().await?;
    tracing::info!("store flushed; stopped");
    Ok(())
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
