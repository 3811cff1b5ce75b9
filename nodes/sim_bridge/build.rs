// mujoco-rs links libmujoco (MUJOCO_DYNAMIC_LINK_DIR, set by .cargo/config.toml) but sets no
// rpath: give this crate's tests and binaries one, so they run without LD_LIBRARY_PATH.
fn main() {
    println!("cargo:rerun-if-env-changed=MUJOCO_DYNAMIC_LINK_DIR");
    if let Ok(dir) = std::env::var("MUJOCO_DYNAMIC_LINK_DIR") {
        // Resolve the clone's .labrig/mujoco link so the rpath survives a moved cache.
        let dir = std::fs::canonicalize(&dir).map(|p| p.display().to_string()).unwrap_or(dir);
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
}
