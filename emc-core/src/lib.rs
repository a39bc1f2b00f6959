//! # emc-core: Extended Morton Codes for `no_std`
//!
//! The encoder core of the emc workspace: code layouts (Morton 30/63, the Extended Morton Codes
//! of Vinkler, Bittner and Havran, HPG 2017, and any custom pattern), numerically stable
//! quantisation, branch-free bit expansion backends with run-time dispatch, and decoders.
//! It needs neither `std` nor `alloc`; firmware and hardware models embed it as it is.
//!
//! ```
//! use emc_core::{Aabb, Encoder, Frame, LayoutSpec};
//! use glam::Vec3;
//!
//! let boxes = [
//!     Aabb::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 1.0, 1.0)),
//!     Aabb::new(Vec3::new(3.0, 1.0, 0.5), Vec3::new(3.5, 2.0, 0.75)),
//! ];
//! let frame = Frame::new(&boxes).unwrap();
//! let spec: LayoutSpec = "emc64-var".parse().unwrap();
//! let enc = Encoder::new(&spec, &frame);
//! let mut codes = [0u64; 2];
//! enc.encode_batch(&boxes, &mut codes).unwrap();
//! println!("{} via {} ({})", enc.layout(), enc.backend(), enc.reason());
//! assert_eq!(enc.decode(codes[1])[0], (1u64 << enc.layout().bit_counts()[0]) - 1);
//! ```
//!
//! Data flow: [`Aabb`] slice → [`Frame`] (bounds, once) → [`LayoutSpec::resolve`] → [`Layout`]
//! → [`Quantizer`] (per-frame constants) → [`Expander`] (backend) → codes.

#![no_std]
#![deny(missing_docs)]
#![warn(clippy::undocumented_unsafe_blocks)]

#[cfg(any(test, feature = "std"))]
extern crate std;

mod aabb;
pub mod cpu;
mod encoder;
mod error;
pub mod expand;
mod frame;
pub mod layout;
pub mod quantize;
pub mod simd;

pub use aabb::Aabb;
pub use encoder::{Choice, Encoder};
pub use error::Error;
pub use expand::{Backend, Expander};
pub use frame::{Frame, SceneBounds};
pub use layout::{Channel, Layout, LayoutSpec, Normalization, Pattern, SizeTransform};
pub use quantize::Quantizer;
pub use simd::{ExpandPath, Pipeline, QuantizePath, SizePath};

pub use glam;
