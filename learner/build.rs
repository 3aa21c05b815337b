//! Embeds libtorch's library directory as an rpath, so the learner's binaries and tests run
//! without LD_LIBRARY_PATH. Reads the same variables torch-sys does (LIBTORCH_LIB overrides).
fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    println!("cargo:rerun-if-env-changed=LIBTORCH_LIB");
    if let Ok(root) = std::env::var("LIBTORCH_LIB").or_else(|_| std::env::var("LIBTORCH")) {
        // Resolve the repository's `.libtorch` symlink so the rpath survives `cargo clean`
        // and names the real install.
        let root = std::fs::canonicalize(&root).map(|p| p.display().to_string()).unwrap_or(root);
        println!("cargo:rustc-link-arg=-Wl,-rpath,{root}/lib");
    }
}
