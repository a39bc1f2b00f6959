//! Extended Morton codes with the core alone (no allocation, no threads): a frame over a few
//! boxes, an `emc64-var` and a `morton63` encoder, the codes printed in hex. Runs in CI:
//! `cargo run -p emc-core --no-default-features --example encode`.

use emc_core::glam::Vec3;
use emc_core::{Aabb, Encoder, Frame, LayoutSpec};

fn main() -> Result<(), emc_core::Error> {
    // Two big boxes and two small ones along a long x axis.
    let boxes = [
        Aabb::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(4.0, 1.0, 1.0)),
        Aabb::new(Vec3::new(10.0, 0.5, 0.2), Vec3::new(10.1, 0.6, 0.3)),
        Aabb::new(Vec3::new(55.0, 0.1, 0.9), Vec3::new(60.0, 0.9, 1.0)),
        Aabb::new(Vec3::new(99.9, 0.0, 0.0), Vec3::new(100.0, 0.01, 0.01)),
    ];
    let frame = Frame::new(&boxes)?;
    for spec in [LayoutSpec::Emc64Var, LayoutSpec::Morton63] {
        let enc = Encoder::new(&spec, &frame);
        println!("{}:", enc.layout());
        for b in &boxes {
            println!("  {:?} .. {:?}  ->  {:016x}", b.min, b.max, enc.encode(b));
        }
    }
    Ok(())
}
