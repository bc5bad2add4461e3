//! The dynamic objects of a walk and how the user moves them: one object is selected (Tab
//! selects the next); T/G move it forward and back and F/H left and right, level and relative
//! to where the eye looks (the walk's W/S and A/D one row over), R/Y down and up, Z/X turn it
//! about the vertical through its centre. A scripted run moves objects in a straight line
//! frame by frame instead (`--object-to`), as [`crate::Walk::script`] moves the eye.
//!
//! A move is a new [`Pose`]: the object is placed again ([`DynamicObject::place`]) and checked
//! against the static scene ([`PlacedObject::check_clear`]), at steps of at most its radius
//! along the way. A pose that would cross a wall or leave the scene, or a way there that
//! would, is refused and the object stays where it was: it stops at the wall, since the field
//! holds no light for an object inside a wall.

use glam::{DQuat, DVec3};
use vlf_core::dynamic::{DynamicObject, ObjectError, PlacedObject, Pose};
use vlf_core::field::LightField;
use vlf_core::render::Bvh;

/// A key held to move or turn the selected object.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ObjectMove {
    Forward,
    Back,
    Left,
    Right,
    Down,
    Up,
    TurnLeft,
    TurnRight,
}

/// At most this many checks along one move (a move of more than this many radii in one frame
/// is checked at steps of more than a radius).
const MAX_SUBSTEPS: u32 = 256;

/// How fast a held key turns an object, in radians per second.
const TURN_PER_SECOND: f64 = std::f64::consts::FRAC_PI_2;

/// A straight path for every object that has an end, over a number of frames.
struct Script {
    from: Vec<DVec3>,
    to: Vec<Option<DVec3>>,
    frames: u64,
    frame: u64,
}

/// The objects of a walk at their current poses (see the module docs).
pub struct Placement {
    objects: Vec<DynamicObject>,
    poses: Vec<Pose>,
    placed: Vec<PlacedObject>,
    selected: usize,
    held: [bool; 8],
    script: Option<Script>,
    /// Moves refused so far (into a wall, out of the scene).
    pub refused: u64,
}

impl Placement {
    /// `objects` at their poses in `field` (whose static scene `bvh` is), each checked clear
    /// of the static scene.
    pub fn new(objects: Vec<(DynamicObject, Pose)>, field: &LightField, bvh: &Bvh) -> Result<Placement, ObjectError> {
        let mut placed = Vec::with_capacity(objects.len());
        for (object, pose) in &objects {
            let p = object.place(pose, &field.scene.normalisation)?;
            p.check_clear(&field.scene, bvh)?;
            placed.push(p);
        }
        let (objects, poses) = objects.into_iter().unzip();
        Ok(Placement {
            objects,
            poses,
            placed,
            selected: 0,
            held: [false; 8],
            script: None,
            refused: 0,
        })
    }

    /// Moves every object with an end in `to` (scene units: the translation its pose ends
    /// with) in a straight line from where it is, over `frames` calls of
    /// [`Placement::advance`] (the last at the end; one frame goes straight there, as
    /// [`crate::Walk::script`] does); the keys do nothing meanwhile.
    pub fn script(&mut self, to: Vec<Option<DVec3>>, frames: u64) -> vlf_core::Result<()> {
        if frames == 0 || to.len() > self.objects.len() || to.iter().flatten().any(|p| !p.is_finite()) {
            return Err(vlf_core::Error::Parameter(format!(
                "a scripted object path needs at most one finite end per object ({} objects) and at least one frame, got {} ends over {frames} frames",
                self.objects.len(),
                to.len()
            )));
        }
        self.script = Some(Script {
            from: self.poses.iter().map(|p| p.translation).collect(),
            to,
            frames,
            frame: 0,
        });
        Ok(())
    }

    /// The objects as they stand.
    pub fn placed(&self) -> &[PlacedObject] {
        &self.placed
    }

    pub fn is_empty(&self) -> bool {
        self.objects.is_empty()
    }

    /// The bounding spheres (centre and radius, VLF frame) of the objects.
    pub fn spheres(&self) -> Vec<(DVec3, f64)> {
        self.placed.iter().map(|p| (p.center, p.radius)).collect()
    }

    /// The selected object's number and name.
    pub fn selected(&self) -> Option<(usize, &str)> {
        self.objects
            .get(self.selected)
            .map(|o| (self.selected, o.name.as_str()))
    }

    /// Selects the next object (after the last, the first).
    pub fn select_next(&mut self) {
        if !self.objects.is_empty() {
            self.selected = (self.selected + 1) % self.objects.len();
        }
    }

    pub fn set(&mut self, m: ObjectMove, pressed: bool) {
        self.held[m as usize] = pressed;
    }

    /// Moves the objects by `seconds` of held keys (at `speed` scene units per second, level
    /// directions taken from `forward`, where the eye looks) or by one frame of the script;
    /// whether any moved. Each new pose is checked in `field` (with `bvh`) and refused where
    /// it is not clear of the static scene.
    pub fn advance(&mut self, seconds: f64, speed: f64, forward: DVec3, field: &LightField, bvh: &Bvh) -> bool {
        let mut wanted: Vec<(usize, Pose)> = Vec::new();
        if let Some(s) = &mut self.script {
            let f = crate::walk::script_fraction(s.frame, s.frames);
            s.frame += 1;
            for (k, to) in s.to.iter().enumerate() {
                if let Some(to) = to {
                    let translation = s.from[k].lerp(*to, f);
                    if translation != self.poses[k].translation {
                        wanted.push((
                            k,
                            Pose {
                                translation,
                                ..self.poses[k]
                            },
                        ));
                    }
                }
            }
        } else if let Some(pose) = self.keyed_pose(seconds, speed, forward, field) {
            wanted.push((self.selected, pose));
        }
        let mut moved = false;
        for (k, pose) in wanted {
            match self.clear_path(k, pose, field, bvh) {
                Ok(p) => {
                    self.poses[k] = pose;
                    self.placed[k] = p;
                    moved = true;
                }
                Err(e) => {
                    self.refused += 1;
                    tracing::debug!("{e}: the object stays where it is");
                }
            }
        }
        moved
    }

    /// Object `k` placed at `pose`, if the way there from its current pose is clear of the
    /// static scene: checked at sub-steps of at most the object's radius (translation and turn
    /// interpolated), so that one long step (a slow frame, a held key, a scripted path over few
    /// frames) cannot carry it through a thin panel or across a block it would not fit
    /// through. A pose whose object lies wholly inside a closed solid is not detected (no
    /// surface is crossed there); steps of at most its radius keep it from getting in.
    fn clear_path(&self, k: usize, pose: Pose, field: &LightField, bvh: &Bvh) -> Result<PlacedObject, ObjectError> {
        let normalisation = &field.scene.normalisation;
        let (from, current) = (self.poses[k], &self.placed[k]);
        // How far the object's farthest point goes (VLF frame): its centre's move, plus what
        // the turn sweeps at its radius. The centre in the object's own coordinates is the
        // point the new pose carries to the new centre.
        let own = from.rotation.inverse() * (normalisation.to_scene(current.center) - from.translation);
        let shift = normalisation.to_vlf(pose.apply(own)) - current.center;
        let sweep = shift.length() + current.radius * from.rotation.angle_between(pose.rotation);
        let steps = if current.radius > 0.0 && sweep.is_finite() {
            (sweep / current.radius).ceil().clamp(1.0, MAX_SUBSTEPS as f64) as u32
        } else {
            1
        };
        for i in 1..steps {
            let f = i as f64 / steps as f64;
            let between = Pose {
                rotation: from.rotation.slerp(pose.rotation, f),
                translation: from.translation.lerp(pose.translation, f),
            };
            self.objects[k]
                .place(&between, normalisation)?
                .check_clear(&field.scene, bvh)?;
        }
        let placed = self.objects[k].place(&pose, normalisation)?;
        placed.check_clear(&field.scene, bvh)?;
        Ok(placed)
    }

    /// The selected object's pose after `seconds` of the held keys, `None` when none is held.
    fn keyed_pose(&self, seconds: f64, speed: f64, forward: DVec3, field: &LightField) -> Option<Pose> {
        let pose = *self.poses.get(self.selected)?;
        let axis = |plus: ObjectMove, minus: ObjectMove| {
            self.held[plus as usize] as i32 as f64 - self.held[minus as usize] as i32 as f64
        };
        let ahead = DVec3::new(forward.x, 0.0, forward.z)
            .try_normalize()
            .unwrap_or(DVec3::NEG_Z);
        let right = ahead.cross(DVec3::Y);
        let step = ahead * axis(ObjectMove::Forward, ObjectMove::Back)
            + right * axis(ObjectMove::Right, ObjectMove::Left)
            + DVec3::Y * axis(ObjectMove::Up, ObjectMove::Down);
        let turn = axis(ObjectMove::TurnLeft, ObjectMove::TurnRight) * TURN_PER_SECOND * seconds;
        if step == DVec3::ZERO && turn == 0.0 {
            return None;
        }
        // Turn about the vertical through the object's centre (scene units), then move.
        let centre = field.scene.normalisation.to_scene(self.placed[self.selected].center);
        let spin = DQuat::from_rotation_y(turn);
        let translation = spin * (pose.translation - centre) + centre;
        Some(Pose {
            rotation: spin * pose.rotation,
            translation: translation + step.normalize_or_zero() * speed * seconds,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vlf_core::propagate::{Options, Propagation, Stop};
    use vlf_core::psf::GridSize;
    use vlf_core::scene::Material;

    /// The bundled Cornell box (geometry only matters here) and its BVH.
    fn cornell() -> (LightField, Bvh) {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/cornell.obj");
        let (scene, _) = vlf_core::scene::load_obj(&path, &Default::default()).unwrap();
        let options = Options {
            directions: 9,
            grid: GridSize::new(16, 8).unwrap(),
            stop: Stop::Iterations(1),
            ..Options::default()
        };
        let field = Propagation::new(scene, options).unwrap().into_field();
        let bvh = Bvh::build(&field.scene);
        (field, bvh)
    }

    /// A cube of half-size 30 around the origin of its own coordinates, placed at `at`.
    fn placement(at: DVec3, field: &LightField, bvh: &Bvh) -> Placement {
        let cube = DynamicObject::cube("cube", DVec3::ZERO, 30.0, 1, Material::grey("grey", 0.5));
        let pose = Pose {
            translation: at,
            ..Pose::IDENTITY
        };
        Placement::new(vec![(cube, pose)], field, bvh).unwrap()
    }

    fn centre(p: &Placement, field: &LightField) -> DVec3 {
        field.scene.normalisation.to_scene(p.placed()[0].center)
    }

    #[test]
    fn keys_move_the_selected_object_level_as_the_eye_looks_and_turn_it_in_place() {
        let (field, bvh) = cornell();
        let mut p = placement(DVec3::new(200.0, 400.0, 200.0), &field, &bvh);
        // Looking along −z and a little down: T moves 50 units along −z in half a second.
        let forward = DVec3::new(0.0, -0.3, -1.0).normalize();
        p.set(ObjectMove::Forward, true);
        assert!(p.advance(0.5, 100.0, forward, &field, &bvh));
        assert!(centre(&p, &field).distance(DVec3::new(200.0, 400.0, 150.0)) < 1e-6);
        p.set(ObjectMove::Forward, false);
        p.set(ObjectMove::Right, true);
        p.set(ObjectMove::Up, true);
        assert!(p.advance(0.5, 100.0, forward, &field, &bvh));
        let moved = DVec3::new(200.0, 400.0, 150.0) + DVec3::new(1.0, 1.0, 0.0).normalize() * 50.0;
        assert!(centre(&p, &field).distance(moved) < 1e-6);
        p.set(ObjectMove::Right, false);
        p.set(ObjectMove::Up, false);
        assert!(
            !p.advance(0.5, 100.0, forward, &field, &bvh),
            "nothing held, nothing moves"
        );
        // A quarter turn in place: the centre stays, a corner goes round it.
        let corner = |p: &Placement| {
            field
                .scene
                .normalisation
                .to_scene(p.placed()[0].scene.surfaces[0].vertices[0])
        };
        let before = corner(&p);
        p.set(ObjectMove::TurnLeft, true);
        assert!(p.advance(1.0, 100.0, forward, &field, &bvh));
        assert!(centre(&p, &field).distance(moved) < 1e-6);
        let turned = DQuat::from_rotation_y(std::f64::consts::FRAC_PI_2) * (before - moved) + moved;
        assert!(corner(&p).distance(turned) < 1e-6, "{} vs {turned}", corner(&p));
    }

    #[test]
    fn an_object_stops_at_a_wall_and_a_script_moves_every_object_with_an_end() {
        let (field, bvh) = cornell();
        let mut p = placement(DVec3::new(200.0, 400.0, 200.0), &field, &bvh);
        p.set(ObjectMove::Down, true);
        for _ in 0..40 {
            p.advance(0.1, 100.0, DVec3::NEG_Z, &field, &bvh);
        }
        // It came down onto the short block (top at y = 165) and stayed above it.
        let low = p.placed()[0].scene.surfaces.iter().flat_map(|s| &s.vertices);
        let low = low
            .map(|&v| field.scene.normalisation.to_scene(v).y)
            .fold(f64::INFINITY, f64::min);
        assert!(p.refused > 0);
        assert!((165.0..175.0).contains(&low), "lowest point at y = {low}");
        assert!(p.placed()[0].check_clear(&field.scene, &bvh).is_ok());
        // A script over 3 frames ends where it says, whatever keys are held.
        let mut p = placement(DVec3::new(200.0, 400.0, 200.0), &field, &bvh);
        p.set(ObjectMove::Left, true);
        let to = DVec3::new(300.0, 380.0, 120.0);
        p.script(vec![Some(to)], 3).unwrap();
        for _ in 0..3 {
            p.advance(0.1, 100.0, DVec3::NEG_Z, &field, &bvh);
        }
        assert!(centre(&p, &field).distance(to) < 1e-6);
        assert!(p.script(vec![Some(to), Some(to)], 3).is_err(), "more ends than objects");
        assert!(p.script(vec![Some(DVec3::NAN)], 3).is_err());
        assert!(p.script(vec![Some(to)], 0).is_err());
        // One long step (a slow frame) to the other side of the short block (x from about 116
        // to 307 at this depth, top at y = 165), low enough to cross it: each end is clear,
        // the way is not.
        let (start, end) = (DVec3::new(60.0, 40.0, 150.0), DVec3::new(370.0, 40.0, 150.0));
        let far = placement(end, &field, &bvh);
        assert!(
            far.placed()[0].check_clear(&field.scene, &bvh).is_ok(),
            "the far end is clear"
        );
        let mut p = placement(start, &field, &bvh);
        p.set(ObjectMove::Right, true);
        assert!(
            !p.advance(3.1, 100.0, DVec3::NEG_Z, &field, &bvh),
            "went through the block"
        );
        assert_eq!(p.refused, 1);
        assert!(centre(&p, &field).distance(start) < 1e-6);
        // The same long step up, in the open, is taken.
        p.set(ObjectMove::Right, false);
        p.set(ObjectMove::Up, true);
        assert!(p.advance(3.1, 100.0, DVec3::NEG_Z, &field, &bvh));
        assert!(centre(&p, &field).distance(start + DVec3::Y * 310.0) < 1e-6);
        // A script of one frame (`--frames 1 --object-to P`) puts the object at P.
        let mut p = placement(DVec3::new(200.0, 400.0, 200.0), &field, &bvh);
        p.script(vec![Some(to)], 1).unwrap();
        assert!(p.advance(0.1, 100.0, DVec3::NEG_Z, &field, &bvh));
        assert!(centre(&p, &field).distance(to) < 1e-6);
    }
}
