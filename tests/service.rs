//! `seamstress serve` end to end: the real binary on `127.0.0.1:0`, driven
//! over HTTP.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use reqwest::multipart::{Form, Part};
use reqwest::{Client, Response, StatusCode};
use serde_json::{json, Value};

mod common;
use common::server::Server;
use needs::needs;

fn assets() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/assets")
}

fn scratch(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("seamstress-service-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn client() -> Client {
    Client::builder()
        .timeout(Duration::from_secs(300))
        .build()
        .unwrap()
}

/// A raw upload: `.glb` or self-contained `.gltf`.
async fn get(c: &Client, s: &Server, path: &str) -> Response {
    c.get(s.url(path)).send().await.unwrap()
}

async fn delete(c: &Client, s: &Server, path: &str) -> Response {
    c.delete(s.url(path)).send().await.unwrap()
}

/// Announces a `.glb` upload of `length` bytes the way curl sends large
/// bodies (`Expect: 100-continue`) and reads the answer without sending the
/// body. A client that pushes the whole body at a server that has already
/// refused it may see the connection reset instead of the answer, so this is
/// how an oversized upload is tested. Returns the status and the JSON body.
fn declared_upload(s: &Server, length: u64) -> (u16, Value) {
    use std::io::{Read, Write};
    let addr = s.base.trim_start_matches("http://");
    let mut tcp = std::net::TcpStream::connect(addr).unwrap();
    tcp.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    write!(
        tcp,
        "POST /v1/jobs?name=big.glb HTTP/1.1\r\nHost: {addr}\r\n\
         Content-Type: model/gltf-binary\r\nContent-Length: {length}\r\n\
         Expect: 100-continue\r\nConnection: close\r\n\r\n"
    )
    .unwrap();
    let mut raw = Vec::new();
    let _ = tcp.read_to_end(&mut raw);
    let text = String::from_utf8_lossy(&raw);
    let status = text
        .split_whitespace()
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no status line in {text:?}"));
    let body = text.split("\r\n\r\n").nth(1).unwrap_or_default();
    let json = match (body.find('{'), body.rfind('}')) {
        (Some(a), Some(b)) => serde_json::from_str(&body[a..=b]).unwrap_or(Value::Null),
        _ => Value::Null,
    };
    (status, json)
}

async fn submit_raw(c: &Client, s: &Server, bytes: Vec<u8>, name: &str, query: &str) -> Response {
    let ct = if name.ends_with(".glb") {
        "model/gltf-binary"
    } else {
        "model/gltf+json"
    };
    c.post(s.url(&format!("/v1/jobs?name={name}{query}")))
        .header("content-type", ct)
        .body(bytes)
        .send()
        .await
        .unwrap()
}

/// A multipart upload of `model` and every other non-model file in its folder.
fn form_for(model: &Path) -> Form {
    let mut form = Form::new().part(
        "model",
        Part::bytes(std::fs::read(model).unwrap())
            .file_name(model.file_name().unwrap().to_string_lossy().into_owned()),
    );
    for e in std::fs::read_dir(model.parent().unwrap()).unwrap() {
        let p = e.unwrap().path();
        let ext = p.extension().and_then(|x| x.to_str()).unwrap_or("");
        if p.is_file() && !matches!(ext, "gltf" | "glb") {
            form = form.part(
                "files",
                Part::bytes(std::fs::read(&p).unwrap())
                    .file_name(p.file_name().unwrap().to_string_lossy().into_owned()),
            );
        }
    }
    form
}

async fn submit_form(c: &Client, s: &Server, form: Form) -> Response {
    c.post(s.url("/v1/jobs"))
        .multipart(form)
        .send()
        .await
        .unwrap()
}

async fn json_of(r: Response) -> (StatusCode, Value) {
    let status = r.status();
    let ct = r
        .headers()
        .get("content-type")
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    let body = r.bytes().await.unwrap();
    let v = serde_json::from_slice(&body).unwrap_or_else(|e| {
        panic!(
            "{status}: not JSON ({e}, {ct}): {}",
            String::from_utf8_lossy(&body)
        )
    });
    assert!(ct.starts_with("application/json"), "{status}: {ct}");
    (status, v)
}

/// Waits for a job to reach a final state.
async fn finish(c: &Client, s: &Server, id: &str) -> Value {
    let deadline = Instant::now() + Duration::from_secs(240);
    loop {
        let r = c
            .get(s.url(&format!("/v1/jobs/{id}")))
            .header("prefer", "wait=20")
            .send()
            .await
            .unwrap();
        let (status, job) = json_of(r).await;
        assert_eq!(status, StatusCode::OK, "{job}");
        let state = job["state"].as_str().unwrap();
        if matches!(state, "succeeded" | "failed" | "canceled") {
            return job;
        }
        assert!(Instant::now() < deadline, "job {id} still {state}");
    }
}

async fn accepted(r: Response) -> Value {
    let location = r
        .headers()
        .get("location")
        .map(|v| v.to_str().unwrap().to_string());
    let (status, job) = json_of(r).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let id = job["id"].as_str().unwrap();
    assert_eq!(location.unwrap(), format!("/v1/jobs/{id}"));
    job
}

async fn file(c: &Client, s: &Server, id: &str, name: &str) -> Vec<u8> {
    let r = get(c, s, &format!("/v1/jobs/{id}/files/{name}")).await;
    assert_eq!(r.status(), StatusCode::OK, "{name}");
    r.bytes().await.unwrap().to_vec()
}

async fn files_of(c: &Client, s: &Server, job: &Value) -> BTreeMap<String, Vec<u8>> {
    let id = job["id"].as_str().unwrap();
    let mut out = BTreeMap::new();
    for f in job["files"].as_array().unwrap() {
        let name = f["name"].as_str().unwrap();
        out.insert(name.to_string(), file(c, s, id, name).await);
    }
    out
}

/// The same GLB with a different JSON chunk: equal work, different bytes
/// (so the result cache does not answer).
fn variant(glb: &[u8], n: u64) -> Vec<u8> {
    let parts = seamstress::model::rewrite::split_glb(glb).unwrap();
    let mut root: Value = serde_json::from_slice(parts.json).unwrap();
    root["extras"] = json!({ "variant": n });
    seamstress::model::rewrite::pack_glb(&serde_json::to_vec(&root).unwrap(), parts.bin)
}

fn without_timings(mut report: Value) -> Value {
    for t in report["textures"].as_array_mut().unwrap() {
        t.as_object_mut().unwrap().remove("timings_ms");
    }
    report
}

/// `process` as the service runs it (which always draws the seams picture).
fn cli_process(model: &Path, out: &Path) {
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("process")
        .arg(model)
        .arg("--out")
        .arg(out)
        .arg("--pictures")
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}: {}",
        model.display(),
        String::from_utf8_lossy(&o.stderr)
    );
}

enum Upload {
    Raw,
    Multipart,
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_shared_model_in_every_form_matches_process() {
    let data = scratch("models");
    let s = Server::start(&data, &["--workers", "2"]);
    let c = client();
    let cases: Vec<(&str, Upload)> = vec![
        (
            "BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb",
            Upload::Raw,
        ),
        (
            "BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb",
            Upload::Multipart,
        ),
        (
            "BoxTextured/BoxTextured-glTF/BoxTextured.gltf",
            Upload::Multipart,
        ),
        (
            "BoxTextured/BoxTextured-glTF-Embedded/BoxTextured.gltf",
            Upload::Raw,
        ),
        (
            "BoxTextured/BoxTextured-glTF-Embedded/BoxTextured.gltf",
            Upload::Multipart,
        ),
        (
            "TextureTransformTest/TextureTransformTest.gltf",
            Upload::Multipart,
        ),
        ("cube/cube_gradient_128.glb", Upload::Raw),
        ("cube/cube_bad_background_100.glb", Upload::Raw),
        ("cube/cube_gradient_1024.glb", Upload::Raw),
        ("Duck/Duck.gltf", Upload::Raw),
        ("blub/blub.glb", Upload::Raw),
        ("Fox/Fox.gltf", Upload::Multipart),
    ];
    // Submit everything first: the server works while the CLI runs.
    let mut jobs = Vec::new();
    for (rel, form) in &cases {
        let path = assets().join(rel);
        let name = path.file_name().unwrap().to_str().unwrap().to_string();
        let r = match form {
            Upload::Raw => submit_raw(&c, &s, std::fs::read(&path).unwrap(), &name, "").await,
            Upload::Multipart => submit_form(&c, &s, form_for(&path)).await,
        };
        jobs.push(accepted(r).await);
    }
    let out = scratch("models-cli");
    let expected: Vec<PathBuf> = {
        let mut done: HashMap<&str, PathBuf> = HashMap::new();
        let mut v = Vec::new();
        for (rel, _) in &cases {
            let dir = done
                .entry(*rel)
                .or_insert_with(|| {
                    let dir = out.join(rel.replace('/', "_"));
                    cli_process(&assets().join(rel), &dir);
                    dir
                })
                .clone();
            v.push(dir);
        }
        v
    };
    for (((rel, _), job), cli) in cases.iter().zip(&jobs).zip(&expected) {
        let job = finish(&c, &s, job["id"].as_str().unwrap()).await;
        assert_eq!(job["state"], "succeeded", "{rel}: {job}");
        let served = files_of(&c, &s, &job).await;
        let mut compared = 0;
        for e in std::fs::read_dir(cli).unwrap() {
            let p = e.unwrap().path();
            let name = p.file_name().unwrap().to_str().unwrap().to_string();
            let theirs = std::fs::read(&p).unwrap();
            let ours = served
                .get(&name)
                .unwrap_or_else(|| panic!("{rel}: the service has no {name}"));
            if name == "report.json" {
                let a: Value = serde_json::from_slice(ours).unwrap();
                let b: Value = serde_json::from_slice(&theirs).unwrap();
                assert_eq!(without_timings(a.clone()), without_timings(b), "{rel}");
                assert_eq!(job["report"], a, "{rel}: job report and report.json");
            } else {
                assert!(ours == &theirs, "{rel}: {name} differs from process output");
            }
            compared += 1;
        }
        assert!(compared >= 3, "{rel}: only {compared} files");
        check_rewritten_model(rel, &job, &served);
    }
    let _ = std::fs::remove_dir_all(&out);
}

/// The rewritten model references every DDS through MSFT_texture_dds, with
/// the erased PNG as the fallback image; a `.glb` carries both in its
/// binary chunk and loads on its own, a `.gltf` loads with the job's files
/// beside it, and either binds the erased texels.
fn check_rewritten_model(rel: &str, job: &Value, files: &BTreeMap<String, Vec<u8>>) {
    let name = job["input"]["name"].as_str().unwrap();
    let main = files
        .get(name)
        .unwrap_or_else(|| panic!("{rel}: no rewritten model {name}"));
    let glb = name.ends_with(".glb");
    let root: Value = if glb {
        let parts = seamstress::model::rewrite::split_glb(main).unwrap();
        serde_json::from_slice(parts.json).unwrap()
    } else {
        serde_json::from_slice(main).unwrap()
    };
    assert!(
        root["extensionsUsed"]
            .as_array()
            .unwrap()
            .contains(&json!("MSFT_texture_dds")),
        "{rel}"
    );
    let images = root["images"].as_array().unwrap();
    for t in job["report"]["textures"].as_array().unwrap() {
        let image = t["image"].as_u64().unwrap() as usize;
        let dds = t["files"]["dds"].as_str().unwrap();
        let erased = t["files"]["erased"].as_str().unwrap();
        let referencing: Vec<&Value> = root["textures"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|tex| tex["source"] == json!(image))
            .collect();
        assert!(!referencing.is_empty(), "{rel}");
        assert_eq!(images[image]["mimeType"], json!("image/png"), "{rel}");
        for tex in referencing {
            let k = tex["extensions"]["MSFT_texture_dds"]["source"]
                .as_u64()
                .unwrap_or_else(|| panic!("{rel}: texture without MSFT_texture_dds"))
                as usize;
            assert_eq!(images[k]["mimeType"], json!("image/vnd-ms.dds"), "{rel}");
            if glb {
                assert!(images[k]["bufferView"].is_u64(), "{rel}: DDS not embedded");
                assert!(
                    images[image]["bufferView"].is_u64(),
                    "{rel}: PNG not embedded"
                );
            } else {
                assert_eq!(images[k]["uri"], json!(dds), "{rel}");
                assert_eq!(images[image]["uri"], json!(erased), "{rel}");
            }
        }
    }
    let beside = if glb { BTreeMap::new() } else { files.clone() };
    let model = seamstress::model::load_from_memory(
        name,
        main,
        &beside,
        &seamstress::model::LoadOptions::default(),
    )
    .unwrap_or_else(|e| panic!("{rel}: the rewritten model does not load: {e}"));
    let textures = job["report"]["textures"].as_array().unwrap();
    assert_eq!(model.bindings.len(), textures.len(), "{rel}");
    for (b, t) in model.bindings.iter().zip(textures) {
        let erased = seamstress::model::Texture::decode(
            &files[t["files"]["erased"].as_str().unwrap()],
            16384,
        )
        .unwrap();
        assert!(
            b.texture.data == erased.data,
            "{rel}: the fallback is not the erased PNG"
        );
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_input_gets_a_4xx_json_error() {
    let data = scratch("negative");
    let s = Server::start(
        &data,
        &[
            "--workers",
            "1",
            "--max-texture-size",
            "200",
            "--max-body",
            "256KiB",
        ],
    );
    let c = client();
    let mut models = Vec::new();
    let mut stack = vec![assets().join("negative")];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if matches!(p.extension().and_then(|x| x.to_str()), Some("gltf" | "glb")) {
                models.push(p);
            }
        }
    }
    assert!(models.len() >= 10);
    for m in &models {
        let name = m.file_name().unwrap().to_str().unwrap();
        for raw in [true, false] {
            let r = if raw && name.ends_with(".glb") {
                submit_raw(&c, &s, std::fs::read(m).unwrap(), name, "").await
            } else if raw {
                continue;
            } else {
                submit_form(&c, &s, form_for(m)).await
            };
            let (status, err) = json_of(r).await;
            assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{name}: {err}");
            assert_eq!(err["code"], "invalid_model", "{name}");
            let msg = err["message"].as_str().unwrap();
            assert!(msg.contains(name) && !msg.contains('\n'), "{name}: {msg}");
        }
    }

    // An upload above --max-body is refused from its headers alone.
    let blub_len = std::fs::metadata(assets().join("blub/blub.glb"))
        .unwrap()
        .len();
    let (status, err) = declared_upload(&s, blub_len);
    assert_eq!(status, 413, "{err}");
    assert_eq!(err["code"], "payload_too_large", "{err}");

    let box_glb = assets().join("BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb");
    let cases: Vec<(Response, StatusCode, &str)> = vec![
        (
            // 211² against a limit of 200, refused before decoding.
            submit_raw(
                &c,
                &s,
                std::fs::read(&box_glb).unwrap(),
                "BoxTextured.glb",
                "",
            )
            .await,
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_model",
        ),
        (
            submit_raw(&c, &s, b"not a model".to_vec(), "x.glb", "").await,
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_model",
        ),
        (
            submit_raw(&c, &s, Vec::new(), "x.gltf", "").await,
            StatusCode::UNPROCESSABLE_ENTITY,
            "invalid_model",
        ),
        (
            submit_raw(
                &c,
                &s,
                std::fs::read(&box_glb).unwrap(),
                "BoxTextured.glb",
                "&mode=sideways",
            )
            .await,
            StatusCode::BAD_REQUEST,
            "invalid_options",
        ),
        (
            c.post(s.url("/v1/jobs"))
                .header("content-type", "text/plain")
                .body("hello")
                .send()
                .await
                .unwrap(),
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "unsupported_media_type",
        ),
        (
            submit_form(
                &c,
                &s,
                Form::new().part("x", Part::bytes(b"{}".to_vec()).file_name("notes.txt")),
            )
            .await,
            StatusCode::BAD_REQUEST,
            "bad_request",
        ),
        (
            submit_form(
                &c,
                &s,
                form_for(&assets().join("cube/cube_gradient_128.glb"))
                    .text("options", "{\"colour\":\"red\"}"),
            )
            .await,
            StatusCode::BAD_REQUEST,
            "invalid_options",
        ),
        (
            submit_form(
                &c,
                &s,
                Form::new().part("m", Part::bytes(b"{}".to_vec()).file_name("../up.gltf")),
            )
            .await,
            StatusCode::BAD_REQUEST,
            "bad_request",
        ),
        (
            get(&c, &s, "/v1/jobs/0123456789abcdef0123456789abcdef").await,
            StatusCode::NOT_FOUND,
            "not_found",
        ),
        (
            c.put(s.url("/v1/jobs")).send().await.unwrap(),
            StatusCode::METHOD_NOT_ALLOWED,
            "method_not_allowed",
        ),
        (
            c.get(s.url("/v2/nothing")).send().await.unwrap(),
            StatusCode::NOT_FOUND,
            "not_found",
        ),
    ];
    for (i, (r, status, code)) in cases.into_iter().enumerate() {
        let (got, err) = json_of(r).await;
        assert_eq!(got, status, "case {i}: {err}");
        assert_eq!(err["code"], code, "case {i}: {err}");
        assert!(err["message"].as_str().is_some_and(|m| !m.is_empty()));
    }

    // A URI leaving the upload is refused, even when the file is uploaded.
    let gltf =
        std::fs::read_to_string(assets().join("BoxTextured/BoxTextured-glTF/BoxTextured.gltf"))
            .unwrap()
            .replace("BoxTextured0.bin", "../BoxTextured0.bin");
    let form = Form::new()
        .part("m", Part::bytes(gltf.into_bytes()).file_name("Escape.gltf"))
        .part(
            "f",
            Part::bytes(
                std::fs::read(assets().join("BoxTextured/BoxTextured-glTF/BoxTextured0.bin"))
                    .unwrap(),
            )
            .file_name("BoxTextured0.bin"),
        );
    let (status, err) = json_of(submit_form(&c, &s, form).await).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    assert!(
        err["message"].as_str().unwrap().contains("refused"),
        "{err}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn queue_limit_cancellation_and_time_limit() {
    let data = scratch("queue");
    let s = Server::start(&data, &["--workers", "1", "--queue-size", "1"]);
    let c = client();
    let cube = std::fs::read(assets().join("cube/cube_gradient_1024.glb")).unwrap();

    let a = accepted(submit_raw(&c, &s, variant(&cube, 1), "a.glb", "").await).await;
    let a_id = a["id"].as_str().unwrap().to_string();
    // Wait until the worker has taken it, so that the queue is empty again.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, j) = json_of(get(&c, &s, &format!("/v1/jobs/{a_id}")).await).await;
        if j["state"] == "running" {
            break;
        }
        assert_eq!(j["state"], "queued", "{j}");
        assert!(Instant::now() < deadline);
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let b = accepted(submit_raw(&c, &s, variant(&cube, 2), "b.glb", "").await).await;
    assert_eq!(b["state"], "queued");
    let r = submit_raw(&c, &s, variant(&cube, 3), "c.glb", "").await;
    assert!(r.headers().get("retry-after").is_some());
    let (status, err) = json_of(r).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{err}");
    assert_eq!(err["code"], "queue_full");

    // Cancel the queued job, then the running one.
    for id in [b["id"].as_str().unwrap(), a_id.as_str()] {
        let (status, j) = json_of(delete(&c, &s, &format!("/v1/jobs/{id}")).await).await;
        assert_eq!(status, StatusCode::OK, "{j}");
        assert_eq!(j["state"], "canceled");
        assert_eq!(finish(&c, &s, id).await["state"], "canceled");
    }
    let r = get(&c, &s, &format!("/v1/jobs/{a_id}/files/report.json")).await;
    assert_eq!(r.status(), StatusCode::CONFLICT);
    // A canceled job is finished: deleting it removes it.
    let r = delete(&c, &s, &format!("/v1/jobs/{a_id}")).await;
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    let r = get(&c, &s, &format!("/v1/jobs/{a_id}")).await;
    assert_eq!(r.status(), StatusCode::NOT_FOUND);
    drop(s);

    // The per-job time limit.
    let s = Server::start(&data, &["--workers", "1", "--job-timeout", "1s"]);
    let j = accepted(submit_raw(&c, &s, variant(&cube, 4), "d.glb", "").await).await;
    let j = finish(&c, &s, j["id"].as_str().unwrap()).await;
    assert_eq!(j["state"], "failed", "{j}");
    assert_eq!(j["error"]["code"], "timeout", "{j}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_token_sees_only_its_own_jobs() {
    let data = scratch("tokens");
    let s = Server::start(
        &data,
        &[
            "--workers",
            "1",
            "--token",
            "alice:secret-a",
            "--token",
            "bob:secret-b",
        ],
    );
    let c = client();
    let glb = std::fs::read(assets().join("cube/cube_bad_background_100.glb")).unwrap();
    let r = c
        .post(s.url("/v1/jobs"))
        .header("content-type", "model/gltf-binary")
        .body(glb.clone())
        .send()
        .await
        .unwrap();
    let (status, err) = json_of(r).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED, "{err}");
    assert_eq!(err["code"], "unauthorized");
    let r = c
        .get(s.url("/v1/jobs"))
        .bearer_auth("secret-c")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::UNAUTHORIZED);

    let r = c
        .post(s.url("/v1/jobs"))
        .bearer_auth("secret-a")
        .header("content-type", "model/gltf-binary")
        .header("prefer", "wait=60")
        .body(glb)
        .send()
        .await
        .unwrap();
    let job = accepted(r).await;
    assert_eq!(job["state"], "succeeded", "{job}");
    let id = job["id"].as_str().unwrap();
    for (path, method) in [
        (format!("/v1/jobs/{id}"), "GET"),
        (format!("/v1/jobs/{id}/files/report.json"), "GET"),
        (format!("/v1/jobs/{id}"), "DELETE"),
    ] {
        let req = if method == "GET" {
            c.get(s.url(&path))
        } else {
            c.delete(s.url(&path))
        };
        let (status, err) = json_of(req.bearer_auth("secret-b").send().await.unwrap()).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{method} {path}: {err}");
    }
    let (_, list) = json_of(
        c.get(s.url("/v1/jobs"))
            .bearer_auth("secret-b")
            .send()
            .await
            .unwrap(),
    )
    .await;
    assert_eq!(list["jobs"], json!([]));
    let (_, list) = json_of(
        c.get(s.url("/v1/jobs"))
            .bearer_auth("secret-a")
            .send()
            .await
            .unwrap(),
    )
    .await;
    assert_eq!(list["jobs"][0]["id"], json!(id));
    let r = c
        .get(s.url(&format!("/v1/jobs/{id}/files/report.json")))
        .bearer_auth("secret-a")
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    // Operations routes need no token.
    for path in ["/healthz", "/readyz", "/metrics", "/openapi.yaml"] {
        let r = c.get(s.url(path)).send().await.unwrap();
        assert_eq!(r.status(), StatusCode::OK, "{path}");
    }

    // Without tokens, a non-loopback address is refused unless told.
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(["serve", "--listen", "0.0.0.0:0", "--data"])
        .arg(&data)
        .env_remove("SEAMSTRESS_TOKENS")
        .env_remove("SEAMSTRESS_INSECURE_OPEN")
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("--insecure-open"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn protocol_idempotency_cache_etags_paging_and_deletion() {
    let data = scratch("protocol");
    let s = Server::start(&data, &["--workers", "2"]);
    let c = client();
    let glb = std::fs::read(assets().join("cube/cube_gradient_128.glb")).unwrap();

    // Submit and wait in one call.
    let r = c
        .post(s.url("/v1/jobs?name=cube.glb&bc1_level=fast"))
        .header("content-type", "model/gltf-binary")
        .header("prefer", "wait=120")
        .header("idempotency-key", "k-1")
        .body(glb.clone())
        .send()
        .await
        .unwrap();
    assert!(r.headers().get("x-request-id").is_some());
    let first = accepted(r).await;
    assert_eq!(first["state"], "succeeded", "{first}");
    assert_eq!(first["options"]["bc1_level"], "fast");
    assert_eq!(first["report"]["input"], "cube.glb");
    assert_eq!(first["progress"]["fraction"], json!(1.0));
    let id = first["id"].as_str().unwrap();

    // Same key, same upload: the same job. Different upload: 422.
    let again = accepted(
        c.post(s.url("/v1/jobs?name=cube.glb&bc1_level=fast"))
            .header("content-type", "model/gltf-binary")
            .header("idempotency-key", "k-1")
            .body(glb.clone())
            .send()
            .await
            .unwrap(),
    )
    .await;
    assert_eq!(again["id"], first["id"]);
    let (status, err) = json_of(
        c.post(s.url("/v1/jobs?name=cube.glb"))
            .header("content-type", "model/gltf-binary")
            .header("idempotency-key", "k-1")
            .body(glb.clone())
            .send()
            .await
            .unwrap(),
    )
    .await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY);
    assert_eq!(err["code"], "idempotency_key_reused");

    // Same bytes and options, no key: a new job answered from the cache.
    let cached = accepted(
        c.post(s.url("/v1/jobs?name=cube.glb&bc1_level=fast"))
            .header("content-type", "model/gltf-binary")
            .body(glb.clone())
            .send()
            .await
            .unwrap(),
    )
    .await;
    assert_ne!(cached["id"], first["id"]);
    assert_eq!(cached["state"], "succeeded");
    assert_eq!(cached["cached"], true);
    assert_eq!(cached["report"], first["report"]);
    let a = files_of(&c, &s, &first).await;
    assert_eq!(files_of(&c, &s, &cached).await, a);

    // Strong ETags and 304.
    let url = s.url(&format!("/v1/jobs/{id}/files/report.json"));
    let r = c.get(&url).send().await.unwrap();
    assert_eq!(r.headers()["content-type"], "application/json");
    let etag = r.headers()["etag"].to_str().unwrap().to_string();
    assert!(etag.starts_with('"') && !etag.starts_with("W/"));
    let r = c
        .get(&url)
        .header("if-none-match", &etag)
        .send()
        .await
        .unwrap();
    assert_eq!(r.status(), StatusCode::NOT_MODIFIED);
    let dds = first["report"]["textures"][0]["files"]["dds"]
        .as_str()
        .unwrap();
    let r = get(&c, &s, &format!("/v1/jobs/{id}/files/{dds}")).await;
    assert_eq!(r.headers()["content-type"], "image/vnd-ms.dds");
    assert!(r.bytes().await.unwrap().starts_with(b"DDS "));
    let r = get(&c, &s, &format!("/v1/jobs/{id}/files/nothing.dds")).await;
    assert_eq!(r.status(), StatusCode::NOT_FOUND);

    // Paging, newest first.
    let (_, p1) = json_of(c.get(s.url("/v1/jobs?limit=1")).send().await.unwrap()).await;
    assert_eq!(p1["jobs"][0]["id"], cached["id"]);
    assert!(p1["jobs"][0].get("report").is_none());
    let cursor = p1["next_cursor"].as_str().unwrap();
    let (_, p2) = json_of(get(&c, &s, &format!("/v1/jobs?limit=1&cursor={cursor}")).await).await;
    assert_eq!(p2["jobs"][0]["id"], first["id"]);
    assert_eq!(p2["next_cursor"], Value::Null);

    // Deleting a finished job removes it and its files, not the cached copy.
    let r = delete(&c, &s, &format!("/v1/jobs/{id}")).await;
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    assert_eq!(
        c.get(&url).send().await.unwrap().status(),
        StatusCode::NOT_FOUND
    );
    assert_eq!(files_of(&c, &s, &cached).await, a);

    // Operations.
    let metrics = get(&c, &s, "/metrics").await.text().await.unwrap();
    for name in [
        "seamstress_queue_depth",
        "seamstress_jobs{state=\"succeeded\"}",
        "seamstress_stage_duration_seconds_bucket{stage=\"process\"",
        "seamstress_bytes_in_total",
        "seamstress_bytes_out_total",
    ] {
        assert!(metrics.contains(name), "{name} missing from /metrics");
    }
    let spec = get(&c, &s, "/openapi.yaml").await.text().await.unwrap();
    assert_eq!(
        spec,
        std::fs::read_to_string(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("openapi.yaml"))
            .unwrap()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killed_server_restarts_and_finishes_every_job() {
    let data = scratch("sigkill");
    // No grace: on SIGTERM the running job goes straight back to the queue.
    let mut s = Server::start(&data, &["--workers", "1", "--grace", "0"]);
    let c = client();
    let cube = std::fs::read(assets().join("cube/cube_gradient_1024.glb")).unwrap();
    let small = std::fs::read(assets().join("cube/cube_gradient_128.glb")).unwrap();
    let mut ids = Vec::new();
    let first = accepted(submit_raw(&c, &s, variant(&cube, 10), "big.glb", "").await).await;
    ids.push(first["id"].as_str().unwrap().to_string());
    for n in 0..3 {
        let j = accepted(submit_raw(&c, &s, variant(&small, n), "small.glb", "").await).await;
        ids.push(j["id"].as_str().unwrap().to_string());
    }
    // Kill it three times while the first job runs and the others wait.
    let mut seen_processes = 0;
    for _ in 0..3 {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let (_, j) = json_of(get(&c, &s, &format!("/v1/jobs/{}", ids[0])).await).await;
            // Running here: on shared stores a dead server's job stays
            // running under its lease until that runs out.
            let here = format!("-{}-", s.child.id());
            let worker = j["worker"].as_str().unwrap_or("");
            if j["state"] == "running" && worker.contains(&here) && j["progress"]["stage"] != "load"
            {
                break;
            }
            assert!(Instant::now() < deadline, "{j}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        let job_processes = running_jobs_of(&data);
        seen_processes += job_processes.len();
        s.kill();
        s.restart();
        // The new server stopped the old server's job process before it
        // started listening: the re-run never shares a folder with it.
        let left: Vec<u32> = running_jobs_of(&data)
            .into_iter()
            .filter(|p| job_processes.contains(p))
            .collect();
        assert!(
            left.is_empty(),
            "job processes outlived their server: {left:?}"
        );
    }
    assert!(seen_processes > 0, "the job runs in a process of its own");
    for id in &ids {
        let j = finish(&c, &s, id).await;
        assert_eq!(j["state"], "succeeded", "{j}");
        let files = files_of(&c, &s, &j).await;
        assert!(files.contains_key("report.json"));
    }
    let (_, first) = json_of(get(&c, &s, &format!("/v1/jobs/{}", ids[0])).await).await;
    assert_eq!(
        first["attempts"], 1,
        "charged for its server's deaths: {first}"
    );
    assert_eq!(first["interruptions"], 3, "{first}");

    // SIGTERM: the running job is re-queued after the grace period and
    // finishes after the next start.
    s.restart();
    let j = accepted(submit_raw(&c, &s, variant(&cube, 11), "big.glb", "").await).await;
    let id = j["id"].as_str().unwrap().to_string();
    loop {
        let (_, j) = json_of(get(&c, &s, &format!("/v1/jobs/{id}")).await).await;
        if j["state"] == "running" {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let killed = Command::new("kill")
        .args(["-TERM", &s.child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let status = s.child.wait().unwrap();
    assert!(status.success(), "{status:?}");
    s.restart();
    let j = finish(&c, &s, &id).await;
    assert_eq!(j["state"], "succeeded", "{j}");
    let _ = std::fs::remove_dir_all(&data);
}

/// The processes running `seamstress run-job` on a scratch folder under
/// `data`.
fn running_jobs_of(data: &Path) -> Vec<u32> {
    let scratch = data.join("tmp");
    let mut pids = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|n| n.parse::<u32>().ok()) else {
            continue;
        };
        let stat = std::fs::read_to_string(e.path().join("stat")).unwrap_or_default();
        let zombie = stat
            .rsplit_once(')')
            .is_some_and(|(_, rest)| rest.trim_start().starts_with('Z'));
        let args = std::fs::read(e.path().join("cmdline")).unwrap_or_default();
        let args: Vec<&[u8]> = args.split(|&b| b == 0).collect();
        let on_scratch = args.windows(2).any(|w| {
            w[0] == b"run-job"
                && std::str::from_utf8(w[1]).is_ok_and(|d| Path::new(d).starts_with(&scratch))
        });
        if on_scratch && !zombie {
            pids.push(pid);
        }
    }
    pids
}

/// Paths and methods of `openapi.yaml`, read line by line: `  /path:` then
/// `    get:` and the like.
fn spec_routes(spec: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut in_paths = false;
    let mut path = None;
    for line in spec.lines().filter(|l| !l.trim().is_empty()) {
        if !line.starts_with(' ') {
            in_paths = line.trim_end() == "paths:";
            continue;
        }
        if !in_paths {
            continue;
        }
        if let Some(p) = line.strip_prefix("  /") {
            path = Some(format!("/{}", p.trim_end().trim_end_matches(':')));
        } else if let (Some(p), Some(m)) = (&path, line.strip_prefix("    ")) {
            let m = m.trim_end().trim_end_matches(':');
            if ["get", "post", "put", "delete", "patch", "head", "options"].contains(&m) {
                out.push((m.to_string(), p.clone()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn every_route_is_in_openapi_and_the_reverse() {
    let spec =
        std::fs::read_to_string(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("openapi.yaml"))
            .unwrap();
    assert!(spec.starts_with("openapi: 3.1"));
    let mut routes = seamstress::service::route_table();
    routes.sort();
    let documented = spec_routes(&spec);
    assert!(documented.len() >= 9, "{documented:?}");
    assert_eq!(routes, documented);
    assert_eq!(seamstress::service::OPENAPI, spec);
}

/// `seamstress serve` run to its end: it is expected to refuse to start,
/// and one still running after 30 s has not (it is stopped, and the test
/// fails rather than waits for it).
fn serve_refused(data: &Path, extra: &[&str]) -> std::process::Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .args(["serve", "--listen", "127.0.0.1:0", "--data"])
        .arg(data)
        .args(extra)
        .env_remove("SEAMSTRESS_TOKENS")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    while child.try_wait().unwrap().is_none() {
        if Instant::now() > deadline {
            let _ = child.kill();
            let o = child.wait_with_output().unwrap();
            panic!("the server started: {}", String::from_utf8_lossy(&o.stdout));
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn uploads_over_the_budget_are_refused_with_the_quantity_named() {
    let data = scratch("budget");
    let s = Server::start(&data, &["--max-memory", "64M"]);
    let c = client();
    // UVs tiling the texture 1000 times: refused however much memory there is.
    let tiled = std::fs::read(common::tiled_duck(1000.0, &scratch("budget-model"))).unwrap();
    let (status, body) = json_of(submit_raw(&c, &s, tiled, "tiled.gltf", "").await).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["code"], "too_large", "{body}");
    let message = body["message"].as_str().unwrap();
    assert!(message.contains("texels covered by triangles"), "{message}");
    // Fox (2048², estimated above 600 MiB) is over this server's 64 MiB.
    let (status, body) =
        json_of(submit_form(&c, &s, form_for(&assets().join("Fox/Fox.gltf"))).await).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{body}");
    assert_eq!(body["code"], "too_large", "{body}");
    let message = body["message"].as_str().unwrap();
    assert!(
        message.contains("estimated memory") && message.contains("64.0 MiB"),
        "{message}"
    );
    // A small model still runs.
    let small = std::fs::read(assets().join("cube/cube_gradient_128.glb")).unwrap();
    let job = accepted(submit_raw(&c, &s, small, "small.glb", "").await).await;
    let job = finish(&c, &s, job["id"].as_str().unwrap()).await;
    assert_eq!(job["state"], "succeeded", "{job}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_server_on_one_data_folder_refuses_and_touches_nothing() {
    let data = scratch("owner");
    let s = Server::start(&data, &["--workers", "1"]);
    let c = client();
    let cube = std::fs::read(assets().join("cube/cube_gradient_1024.glb")).unwrap();
    let job = accepted(submit_raw(&c, &s, cube, "big.glb", "").await).await;
    let id = job["id"].as_str().unwrap().to_string();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let (_, j) = json_of(get(&c, &s, &format!("/v1/jobs/{id}")).await).await;
        if j["state"] != "queued" {
            break;
        }
        assert!(Instant::now() < deadline, "{j}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let o = serve_refused(&data, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("in use by another seamstress server"), "{err}");
    assert!(err.contains(&format!("pid {}", s.child.id())), "{err}");
    let j = finish(&c, &s, &id).await;
    assert_eq!(j["state"], "succeeded", "{j}");
    assert_eq!(j["attempts"], 1, "{j}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_damaged_job_store_is_never_taken_for_an_empty_one() {
    if common::server::on_cluster() {
        eprintln!("skipped: the embedded job store's own damage; PostgreSQL keeps its own");
        return;
    }
    let data = scratch("damaged");
    let mut s = Server::start(&data, &[]);
    let c = client();
    let small = std::fs::read(assets().join("cube/cube_gradient_128.glb")).unwrap();
    let job = accepted(submit_raw(&c, &s, small, "small.glb", "").await).await;
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(finish(&c, &s, &id).await["state"], "succeeded");
    s.kill();
    let folder = data.join("files/jobs").join(&id);
    assert!(folder.exists());
    let store = data.join("jobs.sqlite3");
    for side in ["jobs.sqlite3-wal", "jobs.sqlite3-shm"] {
        let _ = std::fs::remove_file(data.join(side));
    }
    std::fs::write(&store, b"").unwrap();
    let o = serve_refused(&data, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("empty") && err.contains("--rebuild-store"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "{err}");
    assert!(folder.exists(), "the refused start deleted job files");
    std::fs::remove_file(&store).unwrap();
    let o = serve_refused(&data, &[]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing"));
    assert!(folder.exists());
    // Told to rebuild, it starts afresh.
    let s = Server::start(&data, &["--rebuild-store"]);
    let (status, _) = json_of(get(&c, &s, &format!("/v1/jobs/{id}")).await).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
}

/// Every file under `dir` and its bytes.
fn files_under(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    let mut out = BTreeMap::new();
    let mut todo = vec![dir.to_path_buf()];
    while let Some(d) = todo.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                todo.push(p);
            } else {
                out.insert(p.clone(), std::fs::read(&p).unwrap());
            }
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_store_with_a_damaged_page_or_cut_short_is_refused_and_nothing_deleted() {
    if common::server::on_cluster() {
        eprintln!("skipped: the embedded job store's own damage; PostgreSQL keeps its own");
        return;
    }
    let data = scratch("corrupt");
    let mut s = Server::start(&data, &[]);
    let c = client();
    let cube = std::fs::read(assets().join("cube/cube_gradient_128.glb")).unwrap();
    for query in ["", "&mode=global"] {
        let job = accepted(submit_raw(&c, &s, cube.clone(), "cube.glb", query).await).await;
        let job = finish(&c, &s, job["id"].as_str().unwrap()).await;
        assert_eq!(job["state"], "succeeded", "{job}");
    }
    s.kill();
    // Everything the killed server committed into the store's main file,
    // so that the garbage below is what SQLite reads. The page is the root
    // of an index that starting does not read: a server that does not
    // check would start on it and say it is ready.
    let store = data.join("jobs.sqlite3");
    let root: u64 = {
        let conn = rusqlite::Connection::open(&store).unwrap();
        conn.execute_batch("PRAGMA wal_checkpoint(TRUNCATE)")
            .unwrap();
        conn.query_row(
            "SELECT rootpage FROM sqlite_schema WHERE name = 'jobs_finished'",
            [],
            |r| r.get(0),
        )
        .unwrap()
    };
    for side in ["jobs.sqlite3-wal", "jobs.sqlite3-shm"] {
        let _ = std::fs::remove_file(data.join(side));
    }
    let results = files_under(&data.join("files"));
    assert!(
        results
            .keys()
            .filter(|p| p.ends_with("report.json"))
            .count()
            >= 2,
        "{:?}",
        results.keys()
    );
    let good = std::fs::read(&store).unwrap();
    let page = 4096;
    let mut damaged = good.clone();
    for (i, b) in damaged[(root as usize - 1) * page..][..page]
        .iter_mut()
        .enumerate()
    {
        *b = (i * 151 + 7) as u8;
    }
    let cut = good[..good.len() / 2].to_vec();
    for (what, bytes) in [("garbage in a page", damaged), ("cut short", cut)] {
        std::fs::write(&store, &bytes).unwrap();
        let o = serve_refused(&data, &[]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{what}: {err}");
        assert!(err.contains(&store.display().to_string()), "{what}: {err}");
        assert!(err.contains("damaged"), "{what}: {err}");
        assert!(err.contains("--rebuild-store"), "{what}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "{what}: {err}");
        assert_eq!(
            std::fs::read(&store).unwrap(),
            bytes,
            "{what}: the store changed"
        );
        assert!(
            files_under(&data.join("files")) == results,
            "{what}: result files changed"
        );
    }
}

/// A tmpfs of `mb` MiB mounted at `dir` for the life of the value, where
/// this machine lets tests mount (as root); `None` (with a notice) where
/// not, which fails under `SEAMSTRESS_REQUIRE_TOOLS`.
struct SmallDisk(PathBuf);

impl SmallDisk {
    fn mount(dir: &Path, mb: u32) -> Option<SmallDisk> {
        std::fs::create_dir_all(dir).unwrap();
        let ok = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={mb}m"), "tmpfs"])
            .arg(dir)
            .status()
            .is_ok_and(|s| s.success());
        if !ok {
            assert!(
                std::env::var_os("SEAMSTRESS_REQUIRE_TOOLS").is_none(),
                "cannot mount a tmpfs (needs root) and SEAMSTRESS_REQUIRE_TOOLS is set"
            );
            eprintln!("skipped: cannot mount a small tmpfs here (needs root)");
            return None;
        }
        Some(SmallDisk(dir.to_path_buf()))
    }

    fn free(&self) -> u64 {
        use std::os::unix::ffi::OsStrExt;
        let c = std::ffi::CString::new(self.0.as_os_str().as_bytes()).unwrap();
        let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
        assert_eq!(unsafe { libc::statvfs(c.as_ptr(), &mut st) }, 0);
        st.f_bavail as u64 * st.f_frsize as u64
    }

    /// Fills the disk until `left` bytes stay free.
    fn fill_to(&self, left: u64) {
        let path = self.0.join("filler");
        let have = std::fs::metadata(&path).map_or(0, |m| m.len());
        let add = self.free().saturating_sub(left);
        let f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .unwrap();
        use std::io::Write;
        let mut w = std::io::BufWriter::new(f);
        let chunk = vec![1u8; 64 << 10];
        let mut done = 0;
        while done < add {
            let n = chunk.len().min((add - done) as usize);
            w.write_all(&chunk[..n]).unwrap();
            done += n as u64;
        }
        w.flush().unwrap();
        let _ = have;
    }
}

impl Drop for SmallDisk {
    fn drop(&mut self) {
        let _ = Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

#[needs(tmpfs)]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_disk_delays_jobs_and_says_so() {
    if common::server::on_cluster() {
        eprintln!("skipped: a full data folder; the cluster's files live in the object store");
        return;
    }
    let root = scratch("full");
    let Some(disk) = SmallDisk::mount(&root.join("disk"), 16) else {
        return;
    };
    let data = root.join("disk/data");
    let mut s = Server::start(&data, &["--workers", "1", "--min-free", "256K"]);
    let c = client();
    let cube = std::fs::read(assets().join("cube/cube_gradient_1024.glb")).unwrap();
    let (status, _) = json_of(get(&c, &s, "/readyz").await).await;
    assert_eq!(status, StatusCode::OK);

    // Room for the upload and the job's records, not for its results.
    disk.fill_to(cube.len() as u64 + (900 << 10));
    let job = accepted(submit_raw(&c, &s, cube.clone(), "big.glb", "").await).await;
    let id = job["id"].as_str().unwrap().to_string();
    // The job waits for room instead of failing for good.
    tokio::time::sleep(Duration::from_secs(4)).await;
    let (_, j) = json_of(get(&c, &s, &format!("/v1/jobs/{id}")).await).await;
    assert!(
        j["state"] == "queued" || j["state"] == "running",
        "a full disk decided the job: {j}"
    );

    // Below --min-free: not ready, and uploads are refused with 507.
    disk.fill_to(128 << 10);
    let (status, body) = json_of(get(&c, &s, "/readyz").await).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    assert_eq!(body["code"], "storage_low", "{body}");
    let (status, body) = json_of(submit_raw(&c, &s, cube, "big.glb", "").await).await;
    assert_eq!(status, StatusCode::INSUFFICIENT_STORAGE, "{body}");
    assert_eq!(body["code"], "storage_full", "{body}");

    // Space back: ready again, and the job accepted before finishes,
    // uncharged.
    std::fs::remove_file(root.join("disk/filler")).unwrap();
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let (status, _) = json_of(get(&c, &s, "/readyz").await).await;
    assert_eq!(status, StatusCode::OK);
    let j = finish(&c, &s, &id).await;
    assert_eq!(j["state"], "succeeded", "{j}");
    assert_eq!(j["attempts"], 1, "{j}");
    let files = files_of(&c, &s, &j).await;
    assert!(files.contains_key("report.json"));
    s.kill();
    drop(disk);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_that_runs_out_of_memory_fails_alone() {
    let data = scratch("poison");
    // Each job process may map 400 MiB: far too little for Fox's 2048²
    // texture, plenty for a 128² cube.
    let mut s = Server::start(&data, &["--workers", "2", "--job-address-space", "400M"]);
    let c = client();
    let fox = accepted(submit_form(&c, &s, form_for(&assets().join("Fox/Fox.gltf"))).await).await;
    let small = std::fs::read(assets().join("cube/cube_gradient_128.glb")).unwrap();
    let cube = accepted(submit_raw(&c, &s, small, "small.glb", "").await).await;
    let cube = finish(&c, &s, cube["id"].as_str().unwrap()).await;
    assert_eq!(cube["state"], "succeeded", "{cube}");
    let fox = finish(&c, &s, fox["id"].as_str().unwrap()).await;
    assert_eq!(fox["state"], "failed", "{fox}");
    let code = fox["error"]["code"].as_str().unwrap();
    assert!(matches!(code, "too_large" | "crashed"), "{fox}");
    assert!(fox["files"].as_array().unwrap().is_empty(), "{fox}");
    // The same server answered throughout.
    let (status, _) = json_of(get(&c, &s, "/readyz").await).await;
    assert_eq!(status, StatusCode::OK);
    assert!(s.child.try_wait().unwrap().is_none(), "the server died");
    assert!(
        !data.join("tmp").exists()
            || std::fs::read_dir(data.join("tmp"))
                .unwrap()
                .next()
                .is_none()
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn downloads_resume_with_byte_ranges() {
    let data = scratch("ranges");
    let s = Server::start(&data, &[]);
    let c = client();
    let small = std::fs::read(assets().join("cube/cube_gradient_128.glb")).unwrap();
    let job = accepted(submit_raw(&c, &s, small, "small.glb", "").await).await;
    let job = finish(&c, &s, job["id"].as_str().unwrap()).await;
    let f = job["files"]
        .as_array()
        .unwrap()
        .iter()
        .find(|f| f["name"].as_str().unwrap().ends_with(".dds"))
        .unwrap();
    let url = s.url(f["url"].as_str().unwrap());
    let whole = c.get(&url).send().await.unwrap();
    assert_eq!(whole.headers()["accept-ranges"], "bytes");
    let etag = whole.headers()["etag"].to_str().unwrap().to_string();
    let whole = whole.bytes().await.unwrap();
    let len = whole.len();

    let get = |range: &str, if_range: Option<&str>| {
        let mut r = c.get(&url).header("range", range);
        if let Some(tag) = if_range {
            r = r.header("if-range", tag);
        }
        r.send()
    };
    // The head, then the rest: together the file.
    let head = get("bytes=0-99", None).await.unwrap();
    assert_eq!(head.status(), StatusCode::PARTIAL_CONTENT);
    assert_eq!(
        head.headers()["content-range"],
        format!("bytes 0-99/{len}").as_str()
    );
    let mut joined = head.bytes().await.unwrap().to_vec();
    let rest = get("bytes=100-", Some(&etag)).await.unwrap();
    assert_eq!(rest.status(), StatusCode::PARTIAL_CONTENT);
    joined.extend_from_slice(&rest.bytes().await.unwrap());
    assert!(joined == whole, "the two ranges are not the file");
    // Past the end: 416 with the size.
    let (status, body) = json_of(get(&format!("bytes={len}-"), None).await.unwrap()).await;
    assert_eq!(status, StatusCode::RANGE_NOT_SATISFIABLE, "{body}");
    assert_eq!(body["code"], "range_not_satisfiable");
    // Another version's ETag: the whole file.
    let r = get("bytes=0-9", Some("\"other\"")).await.unwrap();
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(r.bytes().await.unwrap().len(), len);

    // `redirect=1`: an object store signs a URL to itself, which serves the
    // same bytes to a client without the store's credentials; a folder
    // store serves the file as before.
    let no_redirects = Client::builder()
        .redirect(reqwest::redirect::Policy::none())
        .build()
        .unwrap();
    let r = no_redirects
        .get(format!("{url}?redirect=1"))
        .send()
        .await
        .unwrap();
    if common::server::on_cluster() {
        assert_eq!(r.status(), StatusCode::TEMPORARY_REDIRECT);
        let signed = r.headers()["location"].to_str().unwrap().to_string();
        let direct = reqwest::get(&signed).await.unwrap();
        assert_eq!(direct.status(), StatusCode::OK, "{signed}");
        assert!(direct.bytes().await.unwrap() == whole);
    } else {
        assert_eq!(r.status(), StatusCode::OK);
        assert!(r.bytes().await.unwrap() == whole);
    }
}

/// A body whose bytes are not what its Content-Type declares is refused
/// for that, not for what the other parser makes of it (a `.gltf` read as
/// GLB misses its `.bin`); a file of another format is named.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_body_unlike_its_content_type_is_named() {
    let data = scratch("mislabelled");
    let s = Server::start(&data, &[]);
    let c = client();
    let post = |ct: &'static str, body: Vec<u8>| {
        c.post(s.url("/v1/jobs?name=BoxTextured.gltf"))
            .header("content-type", ct)
            .body(body)
            .send()
    };
    let gltf =
        std::fs::read(assets().join("BoxTextured/BoxTextured-glTF/BoxTextured.gltf")).unwrap();
    let (status, err) = json_of(post("model/gltf-binary", gltf).await.unwrap()).await;
    assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{err}");
    let message = err["message"].as_str().unwrap();
    assert!(
        message.contains("the body is glTF JSON, not GLB"),
        "{message}"
    );
    let glb = std::fs::read(assets().join("BoxTextured/BoxTextured-glTF-Binary/BoxTextured.glb"))
        .unwrap();
    let (status, err) = json_of(post("model/gltf+json", glb).await.unwrap()).await;
    assert_eq!(status, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{err}");
    let message = err["message"].as_str().unwrap();
    assert!(
        message.contains("the body is GLB, not glTF JSON"),
        "{message}"
    );
    let obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n".to_vec();
    let (status, err) = json_of(submit_raw(&c, &s, obj, "tiny.glb", "").await).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    let message = err["message"].as_str().unwrap();
    assert!(
        message.contains("tiny.glb: a Wavefront OBJ file, not glTF"),
        "{message}"
    );
}
