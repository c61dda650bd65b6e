//! Callbacks against a receiver on 127.0.0.1 that fails its first two
//! deliveries: the third arrives, its signature verifies, and the job
//! shows the attempts; a host off the allow-list is refused at submission.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::path::PathBuf;
use std::sync::mpsc;
use std::time::Duration;

use hmac::{Hmac, Mac};
use serde_json::Value;
use sha2::{Digest, Sha256};

mod common;
use common::server::Server;

/// One request as the receiver saw it: its signature header and body.
struct Delivery {
    signature: String,
    body: Vec<u8>,
}

/// A receiver that answers 500 to its first `failures` requests and 200
/// after; every request goes down the channel.
fn receiver(failures: usize) -> (u16, mpsc::Receiver<Delivery>) {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for (n, stream) in listener.incoming().enumerate() {
            let Ok(mut stream) = stream else { continue };
            let mut reader = BufReader::new(stream.try_clone().unwrap());
            let (mut length, mut signature) = (0usize, String::new());
            loop {
                let mut line = String::new();
                if reader.read_line(&mut line).unwrap_or(0) == 0 || line == "\r\n" {
                    break;
                }
                let (k, v) = line.split_once(':').unwrap_or((&line, ""));
                match k.to_ascii_lowercase().as_str() {
                    "content-length" => length = v.trim().parse().unwrap_or(0),
                    "seamstress-signature" => signature = v.trim().to_string(),
                    _ => {}
                }
            }
            let mut body = vec![0; length];
            reader.read_exact(&mut body).unwrap();
            let status = if n < failures {
                "500 Internal Server Error"
            } else {
                "200 OK"
            };
            let _ = write!(
                stream,
                "HTTP/1.1 {status}\r\ncontent-length: 0\r\nconnection: close\r\n\r\n"
            );
            let _ = tx.send(Delivery { signature, body });
        }
    });
    (port, rx)
}

fn verifies(secret: &str, d: &Delivery) -> bool {
    let Some((t, v1)) = d
        .signature
        .strip_prefix("t=")
        .and_then(|rest| rest.split_once(",v1="))
    else {
        return false;
    };
    let key = Sha256::digest(secret.as_bytes());
    let mut mac = Hmac::<Sha256>::new_from_slice(&key).unwrap();
    mac.update(t.as_bytes());
    mac.update(b".");
    mac.update(&d.body);
    let hex: String = mac
        .finalize()
        .into_bytes()
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect();
    hex == v1
}

fn model() -> Vec<u8> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/assets/cube/cube_gradient_128.glb");
    std::fs::read(p).unwrap()
}

#[test]
fn a_callback_is_retried_until_it_arrives_signed() {
    let (port, deliveries) = receiver(2);
    let data = std::env::temp_dir().join(format!("seamstress-callback-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&data);
    let allow = format!("127.0.0.1:{port}");
    let default = format!("other=http://127.0.0.1:{port}/default");
    let server = Server::start(
        &data,
        &[
            "--token",
            "farm:s3cret",
            "--token",
            "other:pw",
            "--callback-allow",
            &allow,
            "--callback-default",
            &default,
        ],
    );
    let http = reqwest::blocking::Client::new();
    let post = |callback: &str| {
        http.post(server.url("/v1/jobs"))
            .query(&[("name", "cube.glb"), ("callback", callback)])
            .bearer_auth("s3cret")
            .header("content-type", "model/gltf-binary")
            .body(model())
            .send()
            .unwrap()
    };

    // Off the list: another port, a metadata address, another scheme.
    for url in [
        format!("http://127.0.0.1:{}/hook", port.wrapping_add(1)),
        "http://169.254.169.254/latest/meta-data".to_string(),
        format!("ftp://127.0.0.1:{port}/hook"),
    ] {
        let r = post(&url);
        assert_eq!(r.status(), 400, "{url}");
        let e: Value = r.json().unwrap();
        assert_eq!(e["code"], "invalid_callback", "{e}");
    }

    let r = post(&format!("http://127.0.0.1:{port}/hook"));
    assert!(r.status().is_success(), "{}", r.status());
    let job: Value = r.json().unwrap();
    let id = job["id"].as_str().unwrap().to_string();

    let mut got = Vec::new();
    while got.len() < 3 {
        got.push(
            deliveries
                .recv_timeout(Duration::from_secs(60))
                .expect("a delivery within a minute"),
        );
    }
    for d in &got {
        assert!(verifies("s3cret", d), "signature {:?}", d.signature);
        assert!(!verifies("wrong", d));
    }
    let body: Value = serde_json::from_slice(&got[2].body).unwrap();
    assert_eq!(body["id"], id.as_str());
    assert_eq!(body["state"], "succeeded", "{body}");
    assert!(body["report"]["textures"].is_array(), "{body}");
    assert!(deliveries.recv_timeout(Duration::from_secs(3)).is_err());

    // The job shows its deliveries.
    let mut shown = Value::Null;
    for _ in 0..50 {
        shown = http
            .get(server.url(&format!("/v1/jobs/{id}")))
            .bearer_auth("s3cret")
            .send()
            .unwrap()
            .json()
            .unwrap();
        if shown["callback"]["delivered_ms"].is_u64() {
            break;
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_eq!(shown["callback"]["attempts"], 3, "{shown}");
    assert!(shown["callback"]["delivered_ms"].is_u64(), "{shown}");

    // A token's default callback, for jobs that name none.
    let r = http
        .post(server.url("/v1/jobs"))
        .query(&[("name", "cube.glb")])
        .bearer_auth("pw")
        .header("content-type", "model/gltf-binary")
        .body(model())
        .send()
        .unwrap();
    assert!(r.status().is_success(), "{}", r.status());
    let d = deliveries
        .recv_timeout(Duration::from_secs(60))
        .expect("the default callback");
    assert!(verifies("pw", &d), "signature {:?}", d.signature);
    assert!(!verifies("s3cret", &d));
    drop(server);
    let _ = std::fs::remove_dir_all(&data);
}
