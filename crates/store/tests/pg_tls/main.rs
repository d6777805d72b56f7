//! The PostgreSQL engine over TLS (issue 45): a throw-away server started with `ssl=on`, a
//! certificate this test makes (a CA of its own, a server certificate for `localhost` only),
//! and TCP accepted over TLS only. Each `sslmode` connects or is refused as libpq would.
//!
//! Needs PostgreSQL's server binaries (Debian `postgresql`); without them the test says so and
//! passes, except under `CI=true`, where it fails.

use std::error::Error;
use std::path::Path;

use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, KeyPair};
use seasonloc_app::store::Store;
use seasonloc_store::PgStore;
use seasonloc_test_support::postgres::{self, TestServer};

/// A CA: its certificate (PEM), and the parts to sign with.
struct Ca {
    pem: String,
    cert: rcgen::Certificate,
    key: KeyPair,
}

fn ca(name: &str) -> Ca {
    let mut params = CertificateParams::new(Vec::<String>::new()).unwrap();
    params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    params.distinguished_name.push(DnType::CommonName, name);
    let key = KeyPair::generate().unwrap();
    let cert = params.self_signed(&key).unwrap();
    Ca {
        pem: cert.pem(),
        cert,
        key,
    }
}

/// The full error text, with its causes (where rustls says why the handshake failed).
fn chain(e: &dyn Error) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        text.push_str(": ");
        text.push_str(&c.to_string());
        cause = c.source();
    }
    text
}

async fn connect(url: &str) -> Result<PgStore, String> {
    PgStore::connect(url).await.map_err(|e| chain(&e))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_sslmode_connects_or_is_refused_as_libpq_would() {
    let Some(bin) = postgres::require("the PostgreSQL TLS test") else {
        return;
    };
    let ours = ca("seasonloc test CA");
    let theirs = ca("some other CA");
    let mut params = CertificateParams::new(vec!["localhost".to_string()]).unwrap();
    params
        .distinguished_name
        .push(DnType::CommonName, "localhost");
    let server_key = KeyPair::generate().unwrap();
    let server_cert = params
        .signed_by(&server_key, &ours.cert, &ours.key)
        .unwrap();
    let server = tokio::task::spawn_blocking(move || {
        TestServer::start_tls(&bin, &server_cert.pem(), &server_key.serialize_pem())
    })
    .await
    .unwrap()
    .unwrap_or_else(|e| panic!("cannot start PostgreSQL with TLS: {e}"));
    let server = std::sync::Arc::new(server);
    let s = std::sync::Arc::clone(&server);
    let url = tokio::task::spawn_blocking(move || s.database())
        .await
        .unwrap()
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, pem: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, pem).unwrap();
        p
    };
    let our_ca = write("ours.pem", &ours.pem);
    let their_ca = write("theirs.pem", &theirs.pem);
    let with = |host: &str, query: &str| format!("{}?{query}", url.replacen("127.0.0.1", host, 1));
    let root = |p: &Path| p.to_string_lossy().into_owned();

    // verify-full against our CA under the certificate's name: a working store.
    let store = connect(&with(
        "localhost",
        &format!("sslmode=verify-full&sslrootcert={}", root(&our_ca)),
    ))
    .await
    .unwrap();
    store.check().await.unwrap();
    assert!(store.list_maps().await.unwrap().is_empty());
    assert!(store.location().contains("sslmode=verify-full"));

    // The server takes TCP over TLS only, so these connections were encrypted: without TLS
    // it refuses.
    let e = connect(&with("127.0.0.1", "sslmode=disable"))
        .await
        .err()
        .expect("a connection without TLS was accepted");
    assert!(
        e.contains("pg_hba.conf") || e.contains("no encryption"),
        "{e}"
    );

    // A certificate not signed by the CA we trust is refused.
    let e = connect(&with(
        "localhost",
        &format!("sslmode=verify-full&sslrootcert={}", root(&their_ca)),
    ))
    .await
    .err()
    .expect("a certificate of an untrusted CA was accepted");
    assert!(e.to_lowercase().contains("certificate"), "{e}");

    // Under another name (127.0.0.1 is not in the certificate): verify-full refuses,
    // verify-ca (chain only) accepts.
    let e = connect(&with(
        "127.0.0.1",
        &format!("sslmode=verify-full&sslrootcert={}", root(&our_ca)),
    ))
    .await
    .err()
    .expect("a certificate for another name was accepted by verify-full");
    assert!(e.to_lowercase().contains("certificate"), "{e}");
    connect(&with(
        "127.0.0.1",
        &format!("sslmode=verify-ca&sslrootcert={}", root(&our_ca)),
    ))
    .await
    .unwrap();
    // require encrypts without checking the certificate (libpq's meaning), and so does the
    // default, prefer, with a server that offers TLS.
    connect(&with("127.0.0.1", "sslmode=require"))
        .await
        .unwrap();
    connect(&url).await.unwrap();
    // verify-full without a CA file is a clear error before any connection.
    let e = connect(&with("localhost", "sslmode=verify-full"))
        .await
        .err()
        .expect("verify-full without sslrootcert was accepted");
    assert!(e.contains("needs sslrootcert"), "{e}");
}
