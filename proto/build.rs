//! Generates the API's Rust code with the `protoc` vendored by `protoc-bin-vendored`, so a fresh
//! machine needs no system protobuf compiler.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protoc = protoc_bin_vendored::protoc_bin_path()?;
    // SAFETY: `set_var` is unsound only when another thread reads the environment at the same
    // time; this build script has no other thread, and prost-build reads PROTOC after this line.
    unsafe { std::env::set_var("PROTOC", protoc) };
    println!("cargo:rerun-if-changed=vlf/v1/vlf.proto");
    tonic_prost_build::configure().compile_protos(&["vlf/v1/vlf.proto"], &["."])?;
    Ok(())
}
