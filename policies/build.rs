// torch-sys links libtorch (LIBTORCH, set by .cargo/config.toml to the clone's .labrig/libtorch
// link, which scripts/setup.sh makes) but sets no rpath: give this crate's tests and binaries
// one, so they run without LD_LIBRARY_PATH.
//
// It also builds csrc/c10d_shim.cpp, labrig's few C entry points into libtorch's c10d (tch
// binds none of torch.distributed), against libtorch's headers plus gloo's, which the PyPI
// wheel leaves out: Debian's libgloo-dev supplies them (scripts/setup.sh installs it). Only the
// headers: the Gloo code that runs is the copy inside libtorch_cpu.
fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    let Ok(dir) = std::env::var("LIBTORCH") else {
        panic!("LIBTORCH is not set: run scripts/setup.sh (it assembles libtorch and points .cargo/config.toml at it)")
    };
    let dir = std::fs::canonicalize(&dir).map(|p| p.display().to_string()).unwrap_or(dir);
    println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}/lib");
    // labrig-policy-server shares this script for the rpath; the shim comes to it with the
    // labrig-policies library it links.
    if std::env::var("CARGO_PKG_NAME").as_deref() != Ok("labrig-policies") {
        // (A rerun-if-changed naming a file the package lacks would rebuild it every time.)
        return;
    }
    println!("cargo:rerun-if-changed=csrc/c10d_shim.cpp");
    let gloo = std::path::Path::new("/usr/include/gloo/context.h");
    assert!(gloo.is_file(), "{} is missing: install Debian's libgloo-dev (scripts/setup.sh does)", gloo.display());
    cc::Build::new()
        .cpp(true)
        .file("csrc/c10d_shim.cpp")
        .include(format!("{dir}/include"))
        .include(format!("{dir}/include/torch/csrc/api/include"))
        .flag("-std=c++17")
        .flag("-w")
        .define("_GLIBCXX_USE_CXX11_ABI", "1")
        .define("USE_C10D_GLOO", None)
        .opt_level(1)
        .compile("labrig_c10d");
    println!("cargo:rustc-link-lib=dylib=torch_cpu");
    println!("cargo:rustc-link-lib=dylib=c10");
}
