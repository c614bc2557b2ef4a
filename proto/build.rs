//! Compiles `tweezer/v1/*.proto` with protox (a pure-Rust protobuf compiler:
//! no system `protoc`) and generates prost messages and tonic services.

const PROTOS: [&str; 3] = [
    "tweezer/v1/common.proto",
    "tweezer/v1/learner.proto",
    "tweezer/v1/hardware_agent.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    for proto in PROTOS {
        println!("cargo:rerun-if-changed={proto}");
    }
    let descriptors = protox::compile(PROTOS, ["."])?;
    // The descriptor set itself, for gRPC server reflection.
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(
        out.join("tweezer_descriptor.bin"),
        prost::Message::encode_to_vec(&descriptors),
    )?;
    tonic_prost_build::configure().compile_fds(descriptors)?;
    Ok(())
}
