//! TEMPORARY STUB
use crate::scene::Scene;
use glam::DVec3;
pub struct Bvh;
impl Bvh {
    pub fn build(_s: &Scene) -> Self {
        Bvh
    }
}
pub struct Hit {
    pub surface: usize,
    pub t: f64,
    pub point: DVec3,
    pub front: bool,
}
pub struct Camera;
pub struct Image;
pub mod camera {
    pub fn parse_vec3(_s: &str) -> crate::Result<glam::DVec3> {
        todo!()
    }
    pub fn parse_size(_s: &str) -> crate::Result<(u32, u32)> {
        todo!()
    }
}
impl Camera {
    pub fn new(_a: DVec3, _b: DVec3, _c: DVec3, _d: f64, _w: u32, _h: u32) -> crate::Result<Self> {
        todo!()
    }
}
impl Image {
    pub fn save(&self, _p: &std::path::Path, _e: f64) -> crate::Result<()> {
        todo!()
    }
}
pub fn render<F: Fn(&Hit, DVec3) -> [f64; 3] + Sync>(_s: &Scene, _b: &Bvh, _c: &Camera, _n: u32, _f: F) -> Image {
    Image
}
