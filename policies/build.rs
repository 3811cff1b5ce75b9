// torch-sys links libtorch (LIBTORCH, set by .cargo/config.toml to the clone's .labrig/libtorch
// link, which scripts/setup.sh makes) but sets no rpath: give this crate's tests and binaries
// one, so they run without LD_LIBRARY_PATH.
fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    if let Ok(dir) = std::env::var("LIBTORCH") {
        let dir = std::fs::canonicalize(&dir).map(|p| p.display().to_string()).unwrap_or(dir);
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}/lib");
    }
}
