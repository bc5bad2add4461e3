//! (in progress)
use super::*;
#[derive(Clone, Debug, Default)]
pub struct ImportOptions {}
pub fn load_obj(_path: &std::path::Path, _o: &ImportOptions) -> Result<(Scene, Vec<String>), crate::Error> {
    todo!()
}
pub(crate) fn build_scene(
    _p: &[(Vec<DVec3>, usize, FaceOrigin)],
    _m: Vec<Material>,
    _o: &ImportOptions,
    _f: &str,
) -> Result<(Scene, Vec<String>), crate::Error> {
    todo!()
}
