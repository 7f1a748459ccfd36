//! Headless Chromium driven over its DevTools protocol, for the viewer's end-to-end tests:
//! open a page, evaluate JavaScript in it, take a screenshot.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::os::unix::process::CommandExt as _;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::{json, Value};
use tungstenite::stream::MaybeTlsStream;
use tungstenite::{Message, WebSocket};

/// The Chromium binary: `HANDFLOW_CHROMIUM`, else `chromium` or `chromium-browser` on the
/// path. `None` when there is none.
pub fn chromium_binary() -> Option<PathBuf> {
    if let Some(path) = std::env::var_os("HANDFLOW_CHROMIUM") {
        return Some(PathBuf::from(path));
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .flat_map(|dir| ["chromium", "chromium-browser"].map(|name| dir.join(name)))
        .find(|candidate| candidate.is_file())
}

/// The browser's process group, killed when dropped.
struct BrowserProcess(Child);

impl Drop for BrowserProcess {
    fn drop(&mut self) {
        let group = nix::unistd::Pid::from_raw(-(self.0.id() as i32));
        let _ = nix::sys::signal::kill(group, nix::sys::signal::Signal::SIGKILL);
        let _ = self.0.wait();
    }
}

/// A headless Chromium and a DevTools connection to its one page.
pub struct Browser {
    page: WebSocket<MaybeTlsStream<TcpStream>>,
    /// Killed after the connection closes (fields drop in order).
    _process: BrowserProcess,
    next_id: u64,
    _profile: tempfile::TempDir,
}

impl Browser {
    /// Starts `binary` headless with a fresh profile, connects to its page and gives the page
    /// a `width` x `height` viewport.
    pub fn start(binary: &Path, width: u32, height: u32) -> Browser {
        let profile = tempfile::tempdir().expect("a profile folder");
        let child = Command::new(binary)
            .args([
                "--headless=new",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-extensions",
                "--disable-background-networking",
                "--hide-scrollbars",
                "--remote-debugging-port=0",
                &format!("--window-size={width},{height}"),
                &format!("--user-data-dir={}", profile.path().display()),
                "about:blank",
            ])
            .stdin(Stdio::null())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            // Its own process group, so that its helpers (zygote, renderers) go with it.
            .process_group(0)
            .spawn()
            .unwrap_or_else(|e| panic!("starting `{}`: {e}", binary.display()));
        // Stopped however the rest of the start goes.
        let mut child = BrowserProcess(child);
        // Chromium says where its DevTools listen on standard error.
        let stderr = child.0.stderr.take().expect("piped standard error");
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(url) = line.split_whitespace().find(|w| w.starts_with("ws://")) {
                    let _ = tx.send(url.to_owned());
                }
            }
        });
        let browser_url = rx.recv_timeout(Duration::from_secs(30)).expect("Chromium announces its DevTools endpoint");
        let authority = browser_url.trim_start_matches("ws://").split('/').next().expect("host:port").to_owned();
        let page_url = wait_for_page(&authority);
        let (page, _) = tungstenite::connect(page_url.as_str()).expect("connecting to the page's DevTools");
        if let MaybeTlsStream::Plain(stream) = page.get_ref() {
            stream.set_read_timeout(Some(Duration::from_secs(30))).expect("a read timeout");
        }
        let mut browser = Browser { page, _process: child, next_id: 1, _profile: profile };
        // The window's size includes the browser's own bars: the page gets exactly this.
        browser.call(
            "Emulation.setDeviceMetricsOverride",
            json!({ "width": width, "height": height, "deviceScaleFactor": 1, "mobile": false }),
        );
        browser
    }

    /// Calls DevTools method `method`; returns its result (events in between are skipped).
    pub fn call(&mut self, method: &str, params: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        let request = json!({ "id": id, "method": method, "params": params }).to_string();
        self.page.send(Message::text(request)).expect("sending to DevTools");
        loop {
            let message = self.page.read().unwrap_or_else(|e| panic!("DevTools, waiting for `{method}`: {e}"));
            let Message::Text(text) = message else { continue };
            let reply: Value = serde_json::from_str(text.as_str()).expect("DevTools speaks JSON");
            if reply["id"].as_u64() != Some(id) {
                continue;
            }
            if let Some(error) = reply.get("error") {
                panic!("DevTools `{method}` failed: {error}");
            }
            return reply["result"].clone();
        }
    }

    /// Opens `url` in the page.
    pub fn navigate(&mut self, url: &str) {
        self.call("Page.enable", json!({}));
        let result = self.call("Page.navigate", json!({ "url": url }));
        assert!(result.get("errorText").is_none(), "navigating to {url}: {result}");
    }

    /// The value of JavaScript `expression` in the page (thrown exceptions fail the test).
    pub fn evaluate(&mut self, expression: &str) -> Value {
        let result = self.call("Runtime.evaluate", json!({ "expression": expression, "returnByValue": true }));
        if let Some(exception) = result.get("exceptionDetails") {
            panic!("JavaScript `{expression}` threw: {exception}");
        }
        result["result"]["value"].clone()
    }

    /// Evaluates `expression` every 100 ms until `done` accepts its value (which is
    /// returned), failing with the last value after `timeout`.
    pub fn wait_for(&mut self, expression: &str, timeout: Duration, done: impl Fn(&Value) -> bool) -> Value {
        let started = Instant::now();
        loop {
            let value = self.evaluate(expression);
            if done(&value) {
                return value;
            }
            assert!(started.elapsed() < timeout, "waited {timeout:?} for `{expression}`; last value: {value}");
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// A PNG screenshot of the page.
    pub fn screenshot(&mut self) -> Vec<u8> {
        use base64::Engine as _;
        let result = self.call("Page.captureScreenshot", json!({ "format": "png" }));
        let data = result["data"].as_str().expect("screenshot data");
        base64::engine::general_purpose::STANDARD.decode(data).expect("base64 PNG")
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.page.close(None);
        // The process group goes with `child`.
    }
}

/// The DevTools WebSocket of the browser's first page (it appears shortly after start).
fn wait_for_page(authority: &str) -> String {
    let started = Instant::now();
    loop {
        if let Ok((200, body)) = http_get(authority, "/json/list", &[]) {
            if let Ok(Value::Array(targets)) = serde_json::from_str::<Value>(&body) {
                if let Some(url) =
                    targets.iter().find(|t| t["type"] == "page").and_then(|t| t["webSocketDebuggerUrl"].as_str())
                {
                    return url.to_owned();
                }
            }
        }
        assert!(started.elapsed() < Duration::from_secs(30), "Chromium at {authority} shows no page");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// `GET path` from `authority` (`host:port`) over HTTP/1.1 with extra `headers` (`Host`
/// is the authority unless given); the status code and the body.
pub fn http_get(authority: &str, path: &str, headers: &[(&str, &str)]) -> std::io::Result<(u16, String)> {
    let mut stream = TcpStream::connect(authority)?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    let mut request = format!("GET {path} HTTP/1.1\r\nConnection: close\r\n");
    if !headers.iter().any(|(name, _)| name.eq_ignore_ascii_case("host")) {
        request.push_str(&format!("Host: {authority}\r\n"));
    }
    for (name, value) in headers {
        request.push_str(&format!("{name}: {value}\r\n"));
    }
    request.push_str("\r\n");
    stream.write_all(request.as_bytes())?;
    // Read the head, then the body by its length: not every server closes after it.
    let mut response = Vec::new();
    let mut chunk = [0u8; 8192];
    let (head_end, length) = loop {
        let n = stream.read(&mut chunk)?;
        if n == 0 {
            break (response.len(), None);
        }
        response.extend_from_slice(&chunk[..n]);
        if let Some(end) = response.windows(4).position(|w| w == b"\r\n\r\n") {
            let head = String::from_utf8_lossy(&response[..end]).to_ascii_lowercase();
            let length = head
                .lines()
                .find_map(|l| l.strip_prefix("content-length:"))
                .and_then(|v| v.trim().parse::<usize>().ok());
            break (end + 4, length);
        }
    };
    match length {
        Some(length) => {
            while response.len() < head_end + length {
                let n = stream.read(&mut chunk)?;
                if n == 0 {
                    break;
                }
                response.extend_from_slice(&chunk[..n]);
            }
        }
        None => {
            stream.read_to_end(&mut response)?;
        }
    }
    let head = String::from_utf8_lossy(&response[..head_end.min(response.len())]).into_owned();
    let body = String::from_utf8_lossy(&response[head_end.min(response.len())..]).into_owned();
    let status = head.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    Ok((status, body.to_owned()))
}
