//! (in progress)
use glam::DVec3;
#[derive(Debug)]
pub enum PolygonError {}
pub fn newell_normal(_v: &[DVec3]) -> DVec3 {
    todo!()
}
pub fn convex_pieces(_v: &[DVec3]) -> Result<Vec<Vec<DVec3>>, PolygonError> {
    todo!()
}
