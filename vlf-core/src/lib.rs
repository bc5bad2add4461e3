//! # vlf-core: the virtual light field method
//!
//! A *virtual light field* discretises all lines through a scene into `l`
//! directions over the hemisphere ([`directions`]), each carrying an `N × N`
//! grid of parallel rays cut into `m × m` tiles ([`psf`]). Light is shot from
//! the emitters along every ray of every direction, iteration after
//! iteration ([`propagate`]), and the radiance leaving every surface is kept
//! so that any view can later be rendered by look-ups ([`render`]).
//!
//! Read top-down: [`scene`] (input and validation) → [`directions`] →
//! [`psf`] (rasterisation into tiles) → [`maps`] (texel grids on surfaces) →
//! [`propagate`] → [`field`] (the result, saved and loaded) → [`render`].
//!
//! This crate has no networking and no async: servers are thin layers on it.

pub mod direct;
pub mod directions;
pub mod dynamic;
pub mod error;
pub mod field;
pub mod lookup;
pub mod maps;
pub mod parts;
pub mod propagate;
pub mod psf;
pub mod render;
pub mod scene;

pub use error::{Error, Result};
