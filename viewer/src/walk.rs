//! Walkthrough controls: where the eye is and where it looks, moved by the keys and the mouse a
//! person expects (WASD to walk, Q/E down and up, a drag to look, the wheel for speed).
//!
//! Kept apart from the window so that it is plain state, tested without a display.

use glam::DVec3;
use vlf_core::render::Camera;

/// A key that moves the eye.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Move {
    Forward,
    Back,
    Left,
    Right,
    Down,
    Up,
}

/// The walking eye: position, yaw about +y and pitch, in scene units (the scenes' up is +y).
#[derive(Clone, Debug)]
pub struct Walk {
    pub eye: DVec3,
    /// Radians about +y; 0 looks along −z.
    pub yaw: f64,
    /// Radians above the horizon, within ±89°.
    pub pitch: f64,
    /// Scene units per second.
    pub speed: f64,
    /// Vertical field of view in degrees.
    pub fovy: f64,
    held: [bool; 6],
    script: Option<Script>,
}

/// A walk fixed in advance, frame by frame (benchmarks, tests): the eye moves on a straight line
/// while turning at a constant rate.
#[derive(Clone, Debug)]
struct Script {
    from: DVec3,
    to: DVec3,
    yaw: f64,
    turn: f64,
    frames: u64,
    frame: u64,
}

/// How far along its path a script of `frames` frames is at frame `frame` (from 0): 0 at the
/// first frame, 1 at the last and after it. A script of one frame is at its end: its one frame
/// is the last, and a scripted run's screenshot shows the end of the path it was given.
pub(crate) fn script_fraction(frame: u64, frames: u64) -> f64 {
    if frames <= 1 {
        return 1.0;
    }
    frame.min(frames - 1) as f64 / (frames - 1) as f64
}

/// Radians of turn per pixel of mouse drag.
const LOOK_PER_PIXEL: f64 = 0.003;
/// Speed factor per wheel notch.
const SPEED_PER_NOTCH: f64 = 1.25;
const MAX_PITCH: f64 = 89.0 * std::f64::consts::PI / 180.0;

impl Walk {
    /// Stands at `eye` looking at `target`, walking at `speed` scene units per second.
    pub fn new(eye: DVec3, target: DVec3, fovy: f64, speed: f64) -> Walk {
        let d = (target - eye).normalize_or(DVec3::NEG_Z);
        Walk {
            eye,
            yaw: (-d.x).atan2(-d.z),
            pitch: d.y.clamp(-1.0, 1.0).asin().clamp(-MAX_PITCH, MAX_PITCH),
            speed,
            fovy,
            held: [false; 6],
            script: None,
        }
    }

    /// Replaces the keys by a script over `frames` frames: from where the eye is to `to`, turning
    /// `turn_degrees` to the left (about +y) on the way; the last frame is the end, and frame 0
    /// the start where there are two frames or more (a script of one frame is its end, so that
    /// `--frames 1 --to P` draws the view from `P`; see [`script_fraction`]).
    pub fn script(&mut self, to: DVec3, turn_degrees: f64, frames: u64) -> vlf_core::Result<()> {
        if !(to.is_finite() && turn_degrees.is_finite()) || frames == 0 {
            return Err(vlf_core::Error::Parameter(format!(
                "a scripted walk needs a finite end point and turn and at least one frame, got {to}, {turn_degrees}°, {frames} frames"
            )));
        }
        self.script = Some(Script {
            from: self.eye,
            to,
            yaw: self.yaw,
            turn: turn_degrees.to_radians(),
            frames,
            frame: 0,
        });
        Ok(())
    }

    /// The unit view direction.
    pub fn forward(&self) -> DVec3 {
        let (sy, cy) = self.yaw.sin_cos();
        let (sp, cp) = self.pitch.sin_cos();
        DVec3::new(-sy * cp, sp, -cy * cp)
    }

    pub fn set(&mut self, m: Move, pressed: bool) {
        self.held[m as usize] = pressed;
    }

    /// Turns by a mouse drag of `(dx, dy)` pixels (right and down turn right and down).
    pub fn look(&mut self, dx: f64, dy: f64) {
        self.yaw -= dx * LOOK_PER_PIXEL;
        self.pitch = (self.pitch - dy * LOOK_PER_PIXEL).clamp(-MAX_PITCH, MAX_PITCH);
    }

    /// Wheel notches up (positive) walk faster.
    pub fn wheel(&mut self, notches: f64) {
        self.speed = (self.speed * SPEED_PER_NOTCH.powf(notches)).clamp(1e-9, 1e12);
    }

    /// Moves by what the held keys ask over `seconds`: forward and sideways in the horizontal
    /// plane (looking up does not make W climb), Q/E straight down and up.
    ///
    /// A scripted walk ignores the keys and the time: each call is the next frame.
    pub fn advance(&mut self, seconds: f64) {
        if let Some(s) = &mut self.script {
            let f = script_fraction(s.frame, s.frames);
            self.eye = s.from.lerp(s.to, f);
            self.yaw = s.yaw + s.turn * f;
            s.frame += 1;
            return;
        }
        let (sy, cy) = self.yaw.sin_cos();
        let ahead = DVec3::new(-sy, 0.0, -cy);
        let right = DVec3::new(cy, 0.0, -sy);
        let axis =
            |plus: Move, minus: Move| self.held[plus as usize] as i32 as f64 - self.held[minus as usize] as i32 as f64;
        let step = ahead * axis(Move::Forward, Move::Back)
            + right * axis(Move::Right, Move::Left)
            + DVec3::Y * axis(Move::Up, Move::Down);
        if step != DVec3::ZERO {
            self.eye += step.normalize() * self.speed * seconds;
        }
    }

    /// The camera for an image of `width × height`.
    pub fn camera(&self, width: u32, height: u32) -> vlf_core::Result<Camera> {
        Camera::new(self.eye, self.eye + self.forward(), DVec3::Y, self.fovy, width, height)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: DVec3, b: DVec3) -> bool {
        (a - b).length() < 1e-9
    }

    #[test]
    fn starts_looking_at_the_target() {
        let eye = DVec3::new(278.0, 273.0, -800.0);
        for target in [
            DVec3::new(278.0, 273.0, 0.0),
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(500.0, 400.0, -900.0),
        ] {
            let w = Walk::new(eye, target, 40.0, 1.0);
            assert!(close(w.forward(), (target - eye).normalize()), "{target}");
        }
    }

    #[test]
    fn keys_walk_in_the_horizontal_plane_at_the_set_speed() {
        let mut w = Walk::new(DVec3::ZERO, DVec3::new(0.0, 1.0, -1.0), 40.0, 2.0);
        w.set(Move::Forward, true);
        w.advance(0.5);
        // Looking 45° up, W still walks level: 1 unit along −z.
        assert!(close(w.eye, DVec3::new(0.0, 0.0, -1.0)), "{}", w.eye);
        w.set(Move::Forward, false);
        w.set(Move::Right, true);
        w.advance(1.0);
        assert!(close(w.eye, DVec3::new(2.0, 0.0, -1.0)), "{}", w.eye);
        w.set(Move::Right, false);
        w.set(Move::Up, true);
        w.advance(1.0);
        assert!(close(w.eye, DVec3::new(2.0, 2.0, -1.0)), "{}", w.eye);
        // Opposite keys cancel; nothing held stays put.
        w.set(Move::Down, true);
        w.advance(1.0);
        assert!(close(w.eye, DVec3::new(2.0, 2.0, -1.0)), "{}", w.eye);
    }

    #[test]
    fn dragging_turns_and_the_pitch_stops_short_of_the_pole() {
        let mut w = Walk::new(DVec3::ZERO, DVec3::NEG_Z, 40.0, 1.0);
        // A drag to the right turns right (towards +x).
        w.look(100.0, 0.0);
        assert!(w.forward().x > 0.2, "{}", w.forward());
        w.look(0.0, -1e6);
        assert!((w.pitch - MAX_PITCH).abs() < 1e-12);
        assert!(w.camera(4, 3).is_ok(), "a valid camera even looking straight up");
    }

    #[test]
    fn a_script_walks_and_turns_frame_by_frame() {
        let mut w = Walk::new(DVec3::ZERO, DVec3::NEG_Z, 40.0, 1.0);
        w.script(DVec3::new(0.0, 0.0, -4.0), 90.0, 5).unwrap();
        w.set(Move::Right, true);
        let mut eyes = Vec::new();
        for _ in 0..6 {
            w.advance(10.0);
            eyes.push(w.eye);
        }
        // Frame 0 is the start, frame 4 the end; the keys and the time do nothing.
        assert!(close(eyes[0], DVec3::ZERO));
        assert!(close(eyes[2], DVec3::new(0.0, 0.0, -2.0)), "{}", eyes[2]);
        assert!(close(eyes[4], DVec3::new(0.0, 0.0, -4.0)));
        assert!(close(eyes[5], eyes[4]), "stays at the end");
        // A quarter turn to the left: looking along −x.
        assert!(close(w.forward(), DVec3::NEG_X), "{}", w.forward());
        assert!(w.script(DVec3::NAN, 0.0, 3).is_err());
        assert!(w.script(DVec3::ZERO, 0.0, 0).is_err());
    }

    /// `--frames 1 --to P --turn T`: the one frame is drawn from `P`, turned by `T`.
    #[test]
    fn a_script_of_one_frame_is_at_its_end() {
        let mut w = Walk::new(DVec3::ZERO, DVec3::NEG_Z, 40.0, 1.0);
        w.script(DVec3::new(1.0, 2.0, -3.0), 90.0, 1).unwrap();
        w.advance(0.1);
        assert!(close(w.eye, DVec3::new(1.0, 2.0, -3.0)), "{}", w.eye);
        assert!(close(w.forward(), DVec3::NEG_X), "{}", w.forward());
        assert_eq!(script_fraction(0, 2), 0.0);
        assert_eq!(script_fraction(1, 2), 1.0);
        assert_eq!(script_fraction(7, 2), 1.0);
    }

    #[test]
    fn the_wheel_scales_the_speed() {
        let mut w = Walk::new(DVec3::ZERO, DVec3::NEG_Z, 40.0, 1.0);
        w.wheel(2.0);
        assert!((w.speed - 1.5625).abs() < 1e-12);
        w.wheel(-2.0);
        assert!((w.speed - 1.0).abs() < 1e-12);
    }
}
