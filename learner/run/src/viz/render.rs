//! Side views of the crawler (the x–z plane, x to the right) for the gait animation.

use crawler_env::PoseFrame;
use crawler_env::model::{BASE_HALF_EXTENT, FLOOR_Z, LINK_RADIUS, LINK1_LENGTH, LINK2_LENGTH, TIP_HALF_EXTENT};

use super::canvas::{Canvas, Colour, GLYPH, text_width};

/// Rotates `v` by the unit quaternion `(w, x, y, z)`.
fn rotate(q: [f32; 4], v: [f32; 3]) -> [f32; 3] {
    let [w, x, y, z] = q;
    let u = [x, y, z];
    let cross =
        |a: [f32; 3], b: [f32; 3]| [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    let t = cross(u, v).map(|c| 2.0 * c);
    let ut = cross(u, t);
    [v[0] + w * t[0] + ut[0], v[1] + w * t[1] + ut[1], v[2] + w * t[2] + ut[2]]
}

/// A pose's point `local` (in the body frame) in world coordinates.
fn world_point(pose: &[f32; 7], local: [f32; 3]) -> [f32; 3] {
    let r = rotate([pose[3], pose[4], pose[5], pose[6]], local);
    [pose[0] + r[0], pose[1] + r[1], pose[2] + r[2]]
}

/// How a side view maps the world onto the picture.
#[derive(Debug, Clone, Copy)]
pub struct SideView {
    pub width: u32,
    pub height: u32,
    /// Pixels per metre.
    pub scale: f64,
}

impl SideView {
    /// Draws `frame` with the camera centred on the base; `direction` is +1 (forward) or −1
    /// and only sets which way the distance counts.
    pub fn draw(&self, canvas: &mut Canvas, frame: &PoseFrame, start_x: f32, direction: f32) {
        canvas.fill(Colour::Sky);
        let centre_x = f64::from(frame.base[0]);
        let floor_y = f64::from(self.height) * 0.72;
        let to_pixel = |x: f32, z: f32| {
            let px = f64::from(self.width) / 2.0 + (f64::from(x) - centre_x) * self.scale;
            let py = floor_y - (f64::from(z) - f64::from(FLOOR_Z)) * self.scale;
            (px, py)
        };

        // Ground and a 10 cm grid, labelled every 50 cm from the start position.
        let floor_top = floor_y.round() as i32;
        canvas.fill_rect(0, floor_top, self.width as i32, self.height as i32 - floor_top, Colour::Ground);
        let half_span = f64::from(self.width) / 2.0 / self.scale;
        let first = ((centre_x - half_span - f64::from(start_x)) / 0.1).floor() as i64;
        let last = ((centre_x + half_span - f64::from(start_x)) / 0.1).ceil() as i64;
        for i in first..=last {
            let x = f64::from(start_x) + i as f64 * 0.1;
            let (px, _) = to_pixel(x as f32, FLOOR_Z);
            let major = i % 5 == 0;
            let length = if major { 14 } else { 7 };
            canvas.fill_rect(px.round() as i32, floor_top, 1, length, Colour::Black);
            canvas.fill_rect(px.round() as i32, 0, 1, floor_top, if major { Colour::LightGrey } else { Colour::Sky });
            if major {
                let label = format!("{:.1}", i as f64 * 0.1 * f64::from(direction));
                let label = if label == "-0.0" { "0.0".to_string() } else { label };
                canvas.text(px.round() as i32 - text_width(&label, 1) / 2, floor_top + 18, &label, 1, Colour::Black);
            }
        }
        // The start line.
        let (start_px, _) = to_pixel(start_x, FLOOR_Z);
        canvas.fill_rect(start_px.round() as i32 - 1, floor_top - 60, 3, 60, Colour::Red);

        // The base: its four corners in the x–z plane.
        let h = BASE_HALF_EXTENT;
        let corners: Vec<(f64, f64)> = [[h, 0.0, h], [h, 0.0, -h], [-h, 0.0, -h], [-h, 0.0, h]]
            .iter()
            .map(|&c| {
                let p = world_point(&frame.base, c);
                to_pixel(p[0], p[2])
            })
            .collect();
        canvas.fill_polygon(&corners, Colour::Grey);
        for i in 0..4 {
            canvas.line(corners[i], corners[(i + 1) % 4], 2.0, Colour::Black);
        }

        // The links: capsules from their hinge (the body origin) along the body's +x.
        let radius = (f64::from(LINK_RADIUS) * self.scale).max(2.0);
        for (pose, length, colour) in
            [(&frame.link1, LINK1_LENGTH, Colour::Blue), (&frame.link2, LINK2_LENGTH, Colour::Orange)]
        {
            let start = world_point(pose, [0.0, 0.0, 0.0]);
            let end = world_point(pose, [length, 0.0, 0.0]);
            canvas.capsule(to_pixel(start[0], start[2]), to_pixel(end[0], end[2]), radius, colour);
        }
        // Hinges.
        for pose in [&frame.link1, &frame.link2] {
            let p = world_point(pose, [0.0, 0.0, 0.0]);
            let (px, py) = to_pixel(p[0], p[2]);
            canvas.fill_circle(px, py, radius * 0.8, Colour::Black);
        }
        // The tip cube, turned with link 2.
        let t = TIP_HALF_EXTENT;
        let tip: Vec<(f64, f64)> = [[-t, 0.0, t], [t, 0.0, t], [t, 0.0, -t], [-t, 0.0, -t]]
            .iter()
            .map(|&c| {
                let r = rotate([frame.link2[3], frame.link2[4], frame.link2[5], frame.link2[6]], c);
                to_pixel(frame.tip[0] + r[0], frame.tip[2] + r[2])
            })
            .collect();
        canvas.fill_polygon(&tip, Colour::Red);

        // Time stamp and distance marker.
        let distance = (frame.base[0] - start_x) * direction;
        canvas.text(8, 8, &format!("t = {:5.2} s", frame.time), 2, Colour::Black);
        let marker = format!("distance {distance:+.2} m");
        canvas.text(self.width as i32 - 8 - text_width(&marker, 2), 8, &marker, 2, Colour::Black);
        canvas.text(8, 8 + 2 * GLYPH + 6, "side view, grid 10 cm", 1, Colour::Grey);
    }
}

/// Every `stride`-th frame so that frames are `1/fps` apart in simulated time.
pub fn frame_stride(dt: f32, fps: u32) -> usize {
    ((1.0 / (f64::from(fps.max(1)) * f64::from(dt))).round() as usize).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_rotation_turns_x_down_for_a_positive_y_angle() {
        // A rotation of +30° about y: +x points downwards (the MJCF hinge convention).
        let half = 15f32.to_radians();
        let v = rotate([half.cos(), 0.0, half.sin(), 0.0], [1.0, 0.0, 0.0]);
        assert!((v[0] - 30f32.to_radians().cos()).abs() < 1e-6);
        assert!((v[2] + 30f32.to_radians().sin()).abs() < 1e-6);
    }

    #[test]
    fn stride_gives_the_requested_rate() {
        assert_eq!(frame_stride(0.002, 25), 20);
        assert_eq!(frame_stride(0.002, 50), 10);
        assert_eq!(frame_stride(0.5, 25), 1);
    }
}
