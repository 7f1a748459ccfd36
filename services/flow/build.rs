//! Finds the SeetaFace frontal model that the `rustface` package ships inside its crates.io
//! package, so the face detector's model arrives through the registry and nothing is
//! downloaded or committed. The path is handed to the compiler for `include_bytes!`.

use std::path::PathBuf;

const RUSTFACE_VERSION: &str = "0.1.7";
const MODEL: &str = "model/seeta_fd_frontal_v1.0.bin";

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=HANDFLOW_FACE_MODEL");
    let found =
        std::env::var_os("HANDFLOW_FACE_MODEL").map(PathBuf::from).filter(|p| p.is_file()).or_else(find_in_registry);
    match found {
        Some(path) => println!("cargo:rustc-env=HANDFLOW_FACE_MODEL_PATH={}", path.display()),
        None => panic!(
            "handflow-flow: the face detector model ({MODEL} of the rustface {RUSTFACE_VERSION} package) was not \
             found under $CARGO_HOME/registry/src; run `cargo fetch`, or set HANDFLOW_FACE_MODEL to the file"
        ),
    }
}

fn find_in_registry() -> Option<PathBuf> {
    let home = std::env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cargo")))?;
    let src = home.join("registry").join("src");
    let mut candidates: Vec<PathBuf> = std::fs::read_dir(&src)
        .ok()?
        .flatten()
        .map(|index| index.path().join(format!("rustface-{RUSTFACE_VERSION}")).join(MODEL))
        .filter(|p| p.is_file())
        .collect();
    candidates.sort();
    candidates.into_iter().next()
}
