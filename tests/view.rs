//! The view page in a real browser: a server runs a job on Fox with
//! `keep_regular`, headless Chromium opens `GET /v1/jobs/{id}/view` with the
//! job's token, the page flies to a closed seam at a magnification where
//! bilinear filtering shows and screenshots each version; the colour step
//! across the seam line is measured on those screenshots. Also
//! `seamstress view` over a folder `process` wrote serves the same page.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Write};
use std::os::fd::FromRawFd;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine;
use serde_json::{json, Value};

mod common;
use common::server::Server;
use needs::needs;

const TOKEN: &str = "viewer:view-test-token-0123456789";
/// The page's canvas in the probe.
const WIDTH: u32 = 640;
const HEIGHT: u32 = 480;
/// Pixels either side of the seam line compared: a quarter of a texel at
/// the page's 16 pixels per texel, well inside each side's triangles.
const OFFSET: f64 = 4.0;

fn artefacts() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/view-test");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Headless Chromium driven over the DevTools protocol on a pipe (fds 3
/// and 4): no virtual time, so the page's own timings are real, and the
/// page's result is awaited rather than polled from a DOM dump. Killed with
/// its helpers on drop.
struct Browser {
    child: Child,
    to: File,
    from: BufReader<File>,
    next_id: u64,
}

impl Browser {
    fn start(profile: &Path, log: &Path) -> Browser {
        let mut to_child = [0; 2];
        let mut from_child = [0; 2];
        // SAFETY: plain pipe creation; the fds are owned below.
        unsafe {
            assert_eq!(libc::pipe2(to_child.as_mut_ptr(), libc::O_CLOEXEC), 0);
            assert_eq!(libc::pipe2(from_child.as_mut_ptr(), libc::O_CLOEXEC), 0);
        }
        let (child_reads, child_writes) = (to_child[0], from_child[1]);
        let mut cmd = Command::new("chromium");
        cmd.args([
            "--headless=new",
            // Chromium's sandbox does not start as root, which CI runs as.
            "--no-sandbox",
            "--disable-dev-shm-usage",
            "--disable-gpu",
            "--disable-background-networking",
            // WebGL on the CPU, with WEBGL_compressed_texture_s3tc.
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--remote-debugging-pipe",
        ])
        .arg(format!("--user-data-dir={}", profile.display()))
        .arg("about:blank")
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(File::create(log).unwrap())
        .process_group(0);
        // SAFETY: only async-signal-safe calls between fork and exec. The
        // pipe ends go first above every fd in use, so that placing them on
        // 3 and 4 cannot clobber one with the other; dup clears CLOEXEC.
        unsafe {
            cmd.pre_exec(move || {
                let r = libc::fcntl(child_reads, libc::F_DUPFD, 100);
                let w = libc::fcntl(child_writes, libc::F_DUPFD, 100);
                if r < 0 || w < 0 || libc::dup2(r, 3) < 0 || libc::dup2(w, 4) < 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = cmd.spawn().expect("chromium starts");
        // SAFETY: the parent's ends, owned from here; the child's are closed.
        let (to, from) = unsafe {
            libc::close(child_reads);
            libc::close(child_writes);
            (
                File::from_raw_fd(to_child[1]),
                File::from_raw_fd(from_child[0]),
            )
        };
        Browser {
            child,
            to,
            from: BufReader::new(from),
            next_id: 0,
        }
    }

    /// Sends a command and returns its answer, skipping events.
    fn call(&mut self, method: &str, params: Value, session: Option<&str>) -> Value {
        self.next_id += 1;
        let mut msg = json!({ "id": self.next_id, "method": method, "params": params });
        if let Some(s) = session {
            msg["sessionId"] = json!(s);
        }
        let mut bytes = serde_json::to_vec(&msg).unwrap();
        bytes.push(0);
        self.to.write_all(&bytes).expect("chromium reads its pipe");
        loop {
            let mut buf = Vec::new();
            self.from.read_until(0, &mut buf).unwrap();
            assert!(!buf.is_empty(), "chromium closed its pipe during {method}");
            buf.pop();
            let answer: Value = serde_json::from_slice(&buf).unwrap();
            if answer["id"] == json!(self.next_id) {
                return answer;
            }
        }
    }

    /// Opens `url` and returns what the page's `seamstressResult` resolves to.
    fn page_result(&mut self, url: &str) -> Value {
        let target = self.call("Target.createTarget", json!({ "url": url }), None);
        let target = target["result"]["targetId"].as_str().unwrap().to_string();
        let attached = self.call(
            "Target.attachToTarget",
            json!({ "targetId": target, "flatten": true }),
            None,
        );
        let session = attached["result"]["sessionId"]
            .as_str()
            .unwrap()
            .to_string();
        // The first document is about:blank, replaced by the page: its
        // context is destroyed under an early evaluation, which is retried.
        let wait = "new Promise(r => { const t = () => window.seamstressResult \
                    ? r(window.seamstressResult) : setTimeout(t, 50); t(); })";
        for _ in 0..100 {
            let answer = self.call(
                "Runtime.evaluate",
                json!({ "expression": wait, "awaitPromise": true, "returnByValue": true }),
                Some(&session),
            );
            if let Some(text) = answer["result"]["result"]["value"].as_str() {
                return serde_json::from_str(text).unwrap();
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        panic!("the page never gave a result");
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        // SAFETY: signals only the process group started above.
        unsafe { libc::kill(-(self.child.id() as i32), libc::SIGKILL) };
        let _ = self.child.wait();
    }
}

/// Kills the browser's process group if the test outlives `limit`: a hung
/// page then fails the test instead of holding CI.
fn watchdog(browser: &Browser, limit: Duration) {
    let pid = browser.child.id() as i32;
    std::thread::spawn(move || {
        std::thread::sleep(limit);
        // SAFETY: signals only that process group; harmless if it is gone.
        unsafe { libc::kill(-pid, libc::SIGKILL) };
    });
}

fn http() -> reqwest::blocking::Client {
    reqwest::blocking::Client::builder()
        .timeout(Duration::from_secs(120))
        .build()
        .unwrap()
}

/// Submits Fox with `keep_regular` (no mips: the page looks at level 0)
/// and waits for it; returns the job id.
fn run_fox(server: &Server) -> String {
    let fox = std::fs::read(common::shared_assets().join("Fox/Fox.gltf")).unwrap();
    let resp = http()
        .post(server.url("/v1/jobs?name=Fox.gltf&keep_regular=true&mips=false"))
        .bearer_auth(TOKEN.split_once(':').unwrap().1)
        .header("content-type", "model/gltf+json")
        .header("prefer", "wait=120")
        .body(fox)
        .send()
        .unwrap();
    let job: Value = resp.json().unwrap();
    assert_eq!(job["state"], "succeeded", "{job}");
    job["id"].as_str().unwrap().to_string()
}

/// Mean RMS (over RGB, in 8-bit levels) between pixels `OFFSET` either side
/// of the seam line, over the line's points well inside the picture.
fn step_across(png: &image::RgbImage, line: &[[f64; 2]]) -> (f64, usize) {
    let (w, h) = (f64::from(png.width()), f64::from(png.height()));
    let (mut sum, mut n) = (0.0, 0);
    for pair in line.windows(2) {
        let (p, q) = (pair[0], pair[1]);
        let d = [q[0] - p[0], q[1] - p[1]];
        let len = d[0].hypot(d[1]);
        if len == 0.0 {
            continue;
        }
        let normal = [-d[1] / len, d[0] / len];
        let at = |s: f64| [p[0] + s * normal[0], p[1] + s * normal[1]];
        let (a, b) = (at(-OFFSET), at(OFFSET));
        let inside = |c: [f64; 2]| c[0] >= 8.0 && c[1] >= 8.0 && c[0] < w - 8.0 && c[1] < h - 8.0;
        if !inside(a) || !inside(b) {
            continue;
        }
        let px = |c: [f64; 2]| png.get_pixel(c[0] as u32, c[1] as u32).0;
        let (pa, pb) = (px(a), px(b));
        let sq: f64 = (0..3)
            .map(|c| (f64::from(pa[c]) - f64::from(pb[c])).powi(2))
            .sum();
        sum += (sq / 3.0).sqrt();
        n += 1;
    }
    (if n > 0 { sum / n as f64 } else { f64::NAN }, n)
}

/// The page's screenshots of each version at one seam, saved, and the step
/// across the seam on each.
fn probe(browser: &mut Browser, url: &str, tag: &str, extra: &str) -> (Value, Vec<(String, f64)>) {
    let r = browser.page_result(&format!(
        "{url}#token={}&probe=0&width={WIDTH}&height={HEIGHT}{extra}",
        TOKEN.split_once(':').unwrap().1
    ));
    assert_eq!(r["ok"], true, "the page failed: {r}");
    assert_eq!(r["errors"], json!([]), "errors on the page: {r}");
    let mut steps = Vec::new();
    for (mode, shot) in r["shots"].as_object().expect("screenshots") {
        let data = shot["png"].as_str().unwrap();
        let bytes = base64::engine::general_purpose::STANDARD
            .decode(data.trim_start_matches("data:image/png;base64,"))
            .unwrap();
        std::fs::write(artefacts().join(format!("fox-{tag}-{mode}.png")), &bytes).unwrap();
        let png = image::load_from_memory(&bytes).unwrap().to_rgb8();
        assert_eq!(png.dimensions(), (WIDTH, HEIGHT));
        let line: Vec<[f64; 2]> = serde_json::from_value(shot["line"].clone()).unwrap();
        let (step, n) = step_across(&png, &line);
        assert!(n >= 10, "{mode}: the seam crosses only {n} sampled points");
        steps.push((mode.clone(), step));
    }
    (r, steps)
}

fn step(steps: &[(String, f64)], mode: &str) -> f64 {
    steps
        .iter()
        .find(|(m, _)| m == mode)
        .unwrap_or_else(|| panic!("no {mode} screenshot: {steps:?}"))
        .1
}

#[needs(chromium)]
#[test]
fn the_view_page_shows_the_seams_closing() {
    if !common::CHROMIUM.available() {
        return;
    }
    let started = Instant::now();
    let scratch = tempdir("job");
    let server = Server::start(&scratch.join("data"), &["--token", TOKEN]);
    let id = run_fox(&server);
    let job_s = started.elapsed().as_secs_f64();

    // Without the token the job is not there for the page either.
    let page = server.url(&format!("/v1/jobs/{id}/view"));
    let html = http().get(&page).send().unwrap();
    assert_eq!(html.status(), 200);
    assert!(html.text().unwrap().contains("view.js"));
    let anonymous = http()
        .get(server.url(&format!("/v1/jobs/{id}")))
        .send()
        .unwrap();
    assert_eq!(anonymous.status(), 401);

    let mut browser = Browser::start(&scratch.join("profile"), &artefacts().join("chromium.log"));
    watchdog(&browser, Duration::from_secs(90));
    let opened = Instant::now();
    let (r, worst) = probe(&mut browser, &page, "gpu", "");
    let page_s = opened.elapsed().as_secs_f64();
    // The page's own decoder, for browsers without S3TC.
    let (by_page, decoded) = probe(&mut browser, &page, "page-decoder", "&decode=page");
    eprintln!(
        "job {job_s:.1} s; page loaded and rendered in {:.0} ms (page's clock), {page_s:.1} s with \
         the probe; S3TC in WebGL: {}",
        r["load_ms"], r["s3tc"]
    );
    eprintln!("worst closed seam {}: steps {worst:?}", r["edge"]);
    // The README's picture (docs/view-fox-seam.png): a band across the
    // seam from each version, side by side.
    let mut strip = image::RgbImage::new(WIDTH, HEIGHT);
    let band = WIDTH / 4;
    for (k, mode) in ["input", "regular", "seam_aware", "discard"]
        .iter()
        .enumerate()
    {
        let shot = image::open(artefacts().join(format!("fox-gpu-{mode}.png")))
            .unwrap()
            .to_rgb8();
        let view = image::imageops::crop_imm(&shot, (WIDTH - band) / 2, 0, band, HEIGHT);
        image::imageops::replace(&mut strip, &view.to_image(), i64::from(band) * k as i64, 0);
    }
    strip.save(artefacts().join("readme-strip.png")).unwrap();

    assert_eq!(
        r["s3tc"], true,
        "SwiftShader offers S3TC: the GPU path is tested"
    );
    let (input, erased, regular, aware, discard) = (
        step(&worst, "input"),
        step(&worst, "erased"),
        step(&worst, "regular"),
        step(&worst, "seam_aware"),
        step(&worst, "discard"),
    );
    assert!(
        input > 10.0 * regular,
        "input {input:.2}, regular BC1 {regular:.2}"
    );
    assert!(
        regular > aware,
        "regular {regular:.2}, seam-aware {aware:.2}"
    );
    assert!(
        aware < 1.5 && erased < 1.5,
        "seam-aware {aware:.2}, erased {erased:.2}"
    );
    // Discarding taps shows each side's own chart: it removes bilinear
    // bleeding, never the paint. On this seam the sides are painted apart
    // by its jump, so the step stays near it, and never above the input's.
    let jump = r["edge"]["jump"].as_f64().unwrap();
    assert!(
        discard <= input + 1.0,
        "discard {discard:.2}, input {input:.2}"
    );
    assert!(
        (discard - jump).abs() < 0.3 * jump,
        "discard {discard:.2}, jump {jump:.2}"
    );
    assert!(r["load_ms"].as_f64().unwrap() < 2000.0, "{}", r["load_ms"]);
    // The ideal palette in the page and the GPU's decoder differ by a
    // rounding at most: the steps agree.
    assert_eq!(by_page["s3tc"], false);
    for mode in ["regular", "seam_aware"] {
        let (gpu, page) = (step(&worst, mode), step(&decoded, mode));
        assert!(
            (gpu - page).abs() < 0.5,
            "{mode}: GPU {gpu:.2}, page {page:.2}"
        );
    }
    eprintln!("decoded in the page: steps {decoded:?}");
    let _ = std::fs::remove_dir_all(&scratch);
}

fn tempdir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("seamstress-view-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// `seamstress view` prints the page's URL and serves the folder as the
/// service serves a job: the page, the job with the folder's report, and
/// only the folder's files.
#[test]
fn seamstress_view_serves_a_process_folder() {
    let dir = tempdir("cli");
    let out = dir.join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("process")
        .arg(common::shared_assets().join("BoxTextured/BoxTextured-glTF/BoxTextured.gltf"))
        .args(["--no-mips", "--pictures", "--keep-regular", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut child = Command::new(env!("CARGO_BIN_EXE_seamstress"))
        .arg("view")
        .arg(&out)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let mut line = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line.trim().to_string();
    let check = || {
        assert!(
            url.starts_with("http://127.0.0.1:") && url.ends_with("/view"),
            "{url}"
        );
        let client = http();
        let page = client.get(&url).send().unwrap().text().unwrap();
        assert!(page.contains("/v1/view/assets/view.js"), "{page}");
        let base = url.trim_end_matches("/view");
        let job: Value = client.get(base).send().unwrap().json().unwrap();
        assert_eq!(job["state"], "succeeded");
        let files = &job["report"]["textures"][0]["files"];
        for key in ["dds", "regular", "input", "charts", "edges", "erased"] {
            let name = files[key]
                .as_str()
                .unwrap_or_else(|| panic!("no {key}: {files}"));
            let mut body = Vec::new();
            let resp = client.get(format!("{base}/files/{name}")).send().unwrap();
            assert_eq!(resp.status(), 200, "{name}");
            resp.take(u64::MAX).read_to_end(&mut body).unwrap();
            assert_eq!(body, std::fs::read(out.join(name)).unwrap(), "{name}");
        }
        let outside = client
            .get(format!("{base}/files/..%2Freport.json"))
            .send()
            .unwrap();
        assert_eq!(outside.status(), 404);
        let three = client
            .get(url.replace(
                "/v1/jobs/local/view",
                "/v1/view/assets/three/build/three.module.js",
            ))
            .send()
            .unwrap();
        assert_eq!(three.status(), 200);
    };
    let outcome = std::panic::catch_unwind(check);
    let _ = child.kill();
    let _ = child.wait();
    let _ = std::fs::remove_dir_all(&dir);
    if let Err(e) = outcome {
        std::panic::resume_unwind(e);
    }
}
