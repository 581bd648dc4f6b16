//! Signed webhooks (issue 47, item 5): `serve --webhook URL --webhook-secret-file FILE`
//! signs every POST; a receiver we did not write (Python's hmac module,
//! tests/peers/webhook_receiver.py) checks each signature, and a body changed after
//! signing fails it. `--webhook-template FILE` posts the receiver's own fields. An
//! `https://` webhook checks the receiver's certificate.

use std::io::{BufRead as _, BufReader, Write as _};
use std::net::TcpStream;

use coapcam::station::webhook::Template;
use serde_json::Value;

use crate::support::{self, COAPCAM, LIMIT, Proc, TempDir, serve_with, serve_with_env};

/// The receiver's line for the next request it got.
fn next_request(receiver: &mut Proc) -> Value {
    receiver.stdout_line(LIMIT, |l| serde_json::from_str::<Value>(l).ok())
}

/// One measurement recorded by the station at `addr`.
fn measure(addr: std::net::SocketAddr) {
    let uri = format!("coap://{addr}/cams/dimensions");
    Proc::run(COAPCAM, &["post", &uri, "-o", "/dev/null"], LIMIT).expect_success("POST");
}

/// POSTs `body` with the signature header `signature` to the receiver: its status.
fn post(port: u16, signature: &str, body: &str) -> u16 {
    let mut stream = TcpStream::connect(("127.0.0.1", port)).expect("connecting");
    stream.set_read_timeout(Some(LIMIT)).expect("timeout");
    write!(
        stream,
        "POST /hook HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n\
         X-Coapcam-Signature: {signature}\r\nContent-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )
    .expect("sending");
    let mut status = String::new();
    BufReader::new(stream)
        .read_line(&mut status)
        .expect("the status line");
    status
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{status:?}"))
}

#[test]
fn every_post_is_signed_and_a_tampered_body_fails_the_receivers_check() {
    let dir = TempDir::new("webhook-signed");
    let secret = dir.join("secret");
    std::fs::write(&secret, "wh-5f2c9a-not-so-secret\n").expect("writing the secret");
    let secret = secret.to_str().expect("UTF-8 path");
    let script = support::script("webhook_receiver.py");
    let mut receiver = Proc::spawn("python3", &[&script, secret]);
    let port: u16 = receiver.stdout_line(LIMIT, |l| l.strip_prefix("ready ")?.parse().ok());
    let hook = format!("http://127.0.0.1:{port}/hook");

    // The record's JSON, signed.
    let (station, addr) = serve_with(
        &dir.join("a"),
        &[
            "--station-name",
            "dock-a",
            "--webhook",
            &hook,
            "--webhook-secret-file",
            secret,
        ],
    );
    measure(addr);
    measure(addr);
    let mut received = Vec::new();
    for id in [1, 2] {
        let got = next_request(&mut receiver);
        assert_eq!(got["valid"], true, "record {id}: {got}");
        let body: Value =
            serde_json::from_str(got["body"].as_str().expect("a body")).expect("JSON");
        assert_eq!(
            (body["id"].as_u64(), &body["station"]),
            (Some(id), &"dock-a".into())
        );
        support::billed_numbers(&body["measurement"]);
        received.push(got);
    }
    drop(station);

    // The same request again passes; with the body changed after signing it fails.
    let signature = received[1]["signature"].as_str().expect("a signature");
    let body = received[1]["body"].as_str().expect("a body");
    assert_eq!(post(port, signature, body), 204, "sent again unchanged");
    assert!(next_request(&mut receiver)["valid"] == true);
    let tampered = body.replacen("dock-a", "dock-x", 1);
    assert_ne!(tampered, body);
    assert_eq!(post(port, signature, &tampered), 401, "a tampered body");
    assert_eq!(next_request(&mut receiver)["valid"], false);
    let other_time = signature.replacen("t=", "t=1", 1);
    assert_eq!(post(port, &other_time, body), 401, "another time");
    assert_eq!(next_request(&mut receiver)["valid"], false);

    // A template: the receiver's own flat fields, signed too.
    let template = dir.join("template.json");
    std::fs::write(
        &template,
        r#"{"barcode": "/measurement/codes/0/text", "length": "/measurement/length_mm",
            "width": "/measurement/width_mm", "height": "/measurement/height_mm",
            "weight": "/measurement/volumetric_weight_kg", "record": "/id",
            "station": "/station", "unit": "/no-such-field", "format": 2}"#,
    )
    .expect("writing the template");
    let (_station, addr) = serve_with(
        &dir.join("b"),
        &[
            "--station-name",
            "dock-b",
            "--webhook",
            &hook,
            "--webhook-secret-file",
            secret,
            "--webhook-template",
            template.to_str().expect("UTF-8 path"),
        ],
    );
    measure(addr);
    let got = next_request(&mut receiver);
    assert_eq!(got["valid"], true, "{got}");
    let body: Value = serde_json::from_str(got["body"].as_str().expect("a body")).expect("JSON");
    let Value::Object(fields) = &body else {
        panic!("{body}")
    };
    let keys: Vec<&str> = fields.keys().map(String::as_str).collect();
    let mut want = [
        "barcode", "format", "height", "length", "record", "station", "unit", "weight", "width",
    ];
    want.sort_unstable();
    assert_eq!(keys, want, "{body}");
    assert_eq!(body["record"], 1, "{body}");
    assert_eq!(body["station"], "dock-b", "{body}");
    assert_eq!(body["unit"], Value::Null, "a pointer to nothing: {body}");
    assert_eq!(body["format"], 2, "not a pointer: as it is: {body}");
    for dimension in ["length", "width", "height"] {
        assert!(
            body[dimension].as_f64().is_some_and(|mm| mm > 10.0),
            "{dimension}: {body}"
        );
    }
}

/// A self-signed certificate for 127.0.0.1 and its key, as the PEM files `NAME.pem` and
/// `NAME.key` in `dir`.
fn self_signed(dir: &std::path::Path, name: &str) -> (std::path::PathBuf, std::path::PathBuf) {
    self_signed_for(dir, name, None)
}

/// As [`self_signed`], for the host name `host` instead of 127.0.0.1 when one is given.
fn self_signed_for(
    dir: &std::path::Path,
    name: &str,
    host: Option<&str>,
) -> (std::path::PathBuf, std::path::PathBuf) {
    use openssl::asn1::Asn1Time;
    use openssl::hash::MessageDigest;
    use openssl::pkey::PKey;
    use openssl::rsa::Rsa;
    use openssl::x509::extension::SubjectAlternativeName;
    use openssl::x509::{X509Builder, X509NameBuilder};
    let key = PKey::from_rsa(Rsa::generate(2048).expect("an RSA key")).expect("a key");
    let mut subject = X509NameBuilder::new().expect("a name");
    subject
        .append_entry_by_text("CN", name)
        .expect("the common name");
    let subject = subject.build();
    let mut cert = X509Builder::new().expect("a certificate");
    cert.set_version(2).expect("v3");
    cert.set_subject_name(&subject).expect("subject");
    cert.set_issuer_name(&subject).expect("issuer");
    cert.set_pubkey(&key).expect("its key");
    cert.set_not_before(&Asn1Time::days_from_now(0).expect("now"))
        .expect("not before");
    cert.set_not_after(&Asn1Time::days_from_now(1).expect("tomorrow"))
        .expect("not after");
    let mut san = SubjectAlternativeName::new();
    match host {
        Some(host) => san.dns(host),
        None => san.ip("127.0.0.1"),
    };
    let san = san
        .build(&cert.x509v3_context(None, None))
        .expect("its address");
    cert.append_extension(san).expect("the extension");
    cert.sign(&key, MessageDigest::sha256()).expect("signing");
    let (pem, private) = (
        dir.join(format!("{name}.pem")),
        dir.join(format!("{name}.key")),
    );
    std::fs::write(&pem, cert.build().to_pem().expect("PEM")).expect("writing the certificate");
    std::fs::write(&private, key.private_key_to_pem_pkcs8().expect("PEM"))
        .expect("writing the key");
    (pem, private)
}

/// A receiver of `https://` webhooks (tests/peers/webhook_receiver.py), started with the
/// variables `env`, checking signatures with the secret in `dir/secret` and showing a
/// certificate of its own ([`self_signed_for`] `dir`, `name` and `host`).
struct HttpsReceiver {
    process: Proc,
    /// Its URL, the station's `--webhook`.
    hook: String,
    /// The secret's file, the station's `--webhook-secret-file`.
    secret: String,
    /// Its certificate.
    cert: std::path::PathBuf,
}

impl HttpsReceiver {
    fn start(dir: &std::path::Path, name: &str, host: Option<&str>, env: &[(&str, &str)]) -> Self {
        let secret = dir.join("secret");
        std::fs::write(&secret, "wh-tls-secret\n").expect("writing the secret");
        let secret = secret.to_str().expect("UTF-8 path").to_owned();
        let (cert, key) = self_signed_for(dir, name, host);
        let script = support::script("webhook_receiver.py");
        let path = |p: &std::path::Path| p.to_str().expect("UTF-8 path").to_owned();
        let mut process = Proc::spawn_with_env(
            "python3",
            &[&script, &secret, &path(&cert), &path(&key)],
            env,
        );
        let port: u16 = process.stdout_line(LIMIT, |l| l.strip_prefix("ready ")?.parse().ok());
        Self {
            process,
            hook: format!("https://127.0.0.1:{port}/hook"),
            secret,
            cert,
        }
    }
}

/// An `https://` webhook: a receiver whose certificate the station does not trust gets
/// no record (the station gives up the handshake, and keeps the record); trusted
/// (`SSL_CERT_FILE`, OpenSSL's trust store), it gets it, signed.
#[test]
fn an_https_webhook_posts_only_to_a_receiver_whose_certificate_it_trusts() {
    let dir = TempDir::new("webhook-https");
    let mut receiver = HttpsReceiver::start(dir.path(), "receiver", None, &[]);
    let (other, _) = self_signed(dir.path(), "someone-else");
    let flags = [
        "--station-name",
        "dock-tls",
        "--webhook",
        &receiver.hook,
        "--webhook-secret-file",
        &receiver.secret,
    ];
    let state = dir.join("state");
    let (station, addr) = serve_with_env(&state, &flags, &[("SSL_CERT_FILE", &other)]);
    measure(addr);
    let got = next_request(&mut receiver.process);
    assert!(got["tls_refused"].is_string(), "{got}");
    drop(station);
    let (_station, _) = serve_with_env(&state, &flags, &[("SSL_CERT_FILE", &receiver.cert)]);
    let got = next_request(&mut receiver.process);
    assert_eq!(got["valid"], true, "{got}");
    let body: Value = serde_json::from_str(got["body"].as_str().expect("a body")).expect("JSON");
    assert_eq!(
        (body["id"].as_u64(), &body["station"]),
        (Some(1), &"dock-tls".into())
    );
}

/// An `https://` webhook makes its TLS context once, with the trust store as it is at its
/// first connection, and uses it for each connection after: a trust store changed while
/// the station runs changes nothing until it starts again. (Before, each connection made
/// a context of its own and read the trust store again.)
#[test]
fn an_https_webhook_reads_the_trust_store_once_for_all_its_connections() {
    let dir = TempDir::new("webhook-https-once");
    // A new connection for each record.
    let mut receiver = HttpsReceiver::start(
        dir.path(),
        "receiver",
        None,
        &[("WEBHOOK_RECEIVER_CLOSE", "1")],
    );
    let (other, _) = self_signed(dir.path(), "someone-else");
    let trust = dir.join("trust.pem");
    std::fs::copy(&receiver.cert, &trust).expect("trusting the receiver");
    let (_station, addr) = serve_with_env(
        &dir.join("state"),
        &[
            "--webhook",
            &receiver.hook,
            "--webhook-secret-file",
            &receiver.secret,
        ],
        &[("SSL_CERT_FILE", &trust)],
    );
    measure(addr);
    let got = next_request(&mut receiver.process);
    assert_eq!(got["valid"], true, "{got}");
    // The trust store no longer holds the receiver's certificate: the context made at the
    // first connection still does.
    std::fs::copy(&other, &trust).expect("trusting someone else");
    measure(addr);
    let got = next_request(&mut receiver.process);
    assert_eq!(
        got["valid"], true,
        "the second record, on a new connection: {got}"
    );
    let body: Value = serde_json::from_str(got["body"].as_str().expect("a body")).expect("JSON");
    assert_eq!(body["id"], 2, "{body}");
}

/// An `https://` webhook to 127.0.0.1 whose receiver shows a trusted certificate for
/// another host is refused: the handshake is given up, the record waits in the log, and
/// the station's warning says that the certificate is not for 127.0.0.1.
#[test]
fn an_https_webhook_refuses_a_trusted_certificate_for_another_host_and_says_so() {
    let dir = TempDir::new("webhook-https-host");
    let mut receiver =
        HttpsReceiver::start(dir.path(), "elsewhere", Some("elsewhere.example"), &[]);
    let cert = receiver.cert.to_str().expect("UTF-8 path");
    let mut station = support::station_under(
        &[COAPCAM],
        &[("SSL_CERT_FILE", cert)],
        &dir.join("state"),
        &[
            "--webhook",
            &receiver.hook,
            "--webhook-secret-file",
            &receiver.secret,
        ],
    );
    let addr = station.coap;
    measure(addr);
    let got = next_request(&mut receiver.process);
    assert!(got["tls_refused"].is_string(), "{got}");
    let warning = station
        .process
        .stderr_line(LIMIT, |l| l.contains("TLS handshake").then(|| l.to_owned()));
    assert!(
        warning.contains("the server's certificate is not for 127.0.0.1")
            && warning.contains("records wait in the log"),
        "{warning}"
    );
}

#[test]
fn a_missing_secret_file_or_a_bad_template_stops_the_station() {
    let dir = TempDir::new("webhook-bad");
    let state = dir.join("state");
    let state = state.to_str().expect("UTF-8 path");
    let template = dir.join("template.json");
    std::fs::write(&template, r#"{"length": "length_mm"}"#).expect("writing");
    let secret = dir.join("secret");
    std::fs::write(&secret, "\n").expect("writing");
    let base = [
        "serve",
        "--bind",
        "127.0.0.1:0",
        "--state-dir",
        state,
        "--duration",
        "30",
        "--webhook",
        "http://127.0.0.1:9/hook",
    ];
    let cases = [
        (
            vec!["--webhook-secret-file", "/nonexistent/secret"],
            "/nonexistent/secret",
        ),
        (
            vec!["--webhook-secret-file", secret.to_str().expect("UTF-8")],
            "secret is empty",
        ),
        (
            vec!["--webhook-template", template.to_str().expect("UTF-8")],
            "no JSON Pointer",
        ),
    ];
    for (extra, why) in cases {
        let mut args = base.to_vec();
        args.extend(extra);
        let done = Proc::run(COAPCAM, &args, LIMIT);
        assert_eq!(done.status.code(), Some(1), "{args:?}: {}", done.stderr);
        assert!(done.stderr.contains(why), "{why}: {}", done.stderr);
        assert!(
            !done.stderr.contains("serving on"),
            "it did not serve: {}",
            done.stderr
        );
    }
}

#[test]
fn the_template_of_the_docs_fills_a_record() {
    let example = include_str!("../../../../docs/station.md")
        .split("*Templated.*")
        .nth(1)
        .and_then(|s| s.split("```json\n").nth(1))
        .and_then(|s| s.split("```").next())
        .expect("docs/station.md's template");
    let template = Template::parse(example).expect("the docs' template");
    let record = serde_json::json!({
        "id": 7, "station": "dock-1",
        "measurement": {"length_mm": 400.0, "width_mm": 300.0, "height_mm": 200.0,
                        "volumetric_weight_kg": 4.0, "codes": [{"kind": "qr", "text": "PKG-7"}]}
    });
    assert_eq!(
        template.fill(&record),
        serde_json::json!({"barcode": "PKG-7", "length": 400.0, "width": 300.0,
                           "height": 200.0, "weight": 4.0, "station": "dock-1", "record": 7})
    );
}
