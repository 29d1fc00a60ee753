//! FruitEstimates: one trolley's fruits, owning planner → dashboard (also the simulator's truth).

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};
use glasshouse_geom::{FruitEstimate, FruitSolid, FruitSurface, Rgb, SolidKind};
use nalgebra::{Point3, Quaternion, UnitQuaternion, Vector3};

use super::convert::{content, payload, string_or_empty, unit_rotation};
use crate::{fb, MessageKind, Result, Wire};

/// One trolley's fruits: each the one fruit type, [`FruitEstimate`], as the planner found it
/// (or the simulator's truth). On the wire its values are `f32`, except the solid's rotation.
#[derive(Clone, Debug, PartialEq)]
pub struct FruitEstimates {
    pub fruits: Vec<FruitEstimate>,
    pub based_on_seq: u64,
    pub planner_id: String,
    /// The ownership epoch of the owner that estimated them (0: none, e.g. the simulator's
    /// truth).
    pub owner_epoch: u64,
    /// The trolley's visit of its row these fruits are from (0: the first).
    pub visit: u32,
    /// Every fruit of the row's season, the current visit's and the earlier ones' (empty: none
    /// known, or a sender without histories).
    pub history: Vec<FruitHistory>,
}

/// One fruit on one visit: centre in the first visit's frame, world axes, metres.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FruitVisit {
    pub visit: u32,
    pub centre: Point3<f64>,
    /// The size of the fruit's box.
    pub size_m: Vector3<f64>,
    /// The fitted solid's volume, else the box's.
    pub volume_m3: f64,
    /// Its mean observed colour on that visit ([`FruitEstimate::colour`]); `None`: unknown.
    pub colour: Option<Rgb>,
    /// Its volume over the record before it, measured on one shape; `None`: not measured.
    pub volume_ratio: Option<f64>,
}

/// A fruit over the visits of its row: its season id, its estimate's id on the current visit
/// (0: not seen on it), its records oldest first.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FruitHistory {
    pub season_id: u32,
    pub fruit_id: u32,
    pub visits: Vec<FruitVisit>,
    /// The solid and surface of its last record, to measure the next visit's growth against
    /// (MapSnapshots carry it; FruitEstimates leave it out).
    pub last_surface: Option<FruitSurface>,
}

type HistoryVector<'a> =
    flatbuffers::Vector<'a, flatbuffers::ForwardsUOffset<fb::FruitHistory<'a>>>;

/// A history's visit records as the wire's structs.
fn fb_visits(visits: &[FruitVisit]) -> Vec<fb::FruitVisit> {
    let record = |v: &FruitVisit| {
        let (centre, size) = (vec3(&v.centre.coords), vec3(&v.size_m));
        fb::FruitVisit::new(v.visit, &centre, &size, v.volume_m3 as f32)
    };
    visits.iter().map(record).collect()
}

/// Writes fruit histories (FruitEstimates' and MapSnapshot's).
pub(super) fn write_histories<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    histories: &[FruitHistory],
) -> WIPOffset<HistoryVector<'a>> {
    let tables: Vec<_> = histories
        .iter()
        .map(|h| {
            let visits = fb_visits(&h.visits);
            let visits = fbb.create_vector(&visits);
            let (colours, colour_known) = write_visit_colours(fbb, &h.visits);
            let measured = h.visits.iter().any(|v| v.volume_ratio.is_some());
            let ratios: Vec<f32> = h
                .visits
                .iter()
                .map(|v| v.volume_ratio.map_or(f32::NAN, |r| r as f32))
                .collect();
            let volume_ratios = measured.then(|| fbb.create_vector(&ratios));
            let last_solid = h.last_surface.as_ref().map(|s| write_solid(fbb, &s.solid));
            let last_surface = h.last_surface.as_ref().map(|s| {
                let points: Vec<fb::Vec3> = s.points_m.iter().map(|p| vec3(&p.coords)).collect();
                fbb.create_vector(&points)
            });
            fb::FruitHistory::create(
                fbb,
                &fb::FruitHistoryArgs {
                    season_id: h.season_id,
                    fruit_id: h.fruit_id,
                    visits: Some(visits),
                    colours,
                    colour_known,
                    volume_ratios,
                    last_solid,
                    last_surface,
                },
            )
        })
        .collect();
    fbb.create_vector(&tables)
}

type ColourVectors<'a> = (
    Option<WIPOffset<flatbuffers::Vector<'a, fb::Rgb>>>,
    Option<WIPOffset<flatbuffers::Vector<'a, bool>>>,
);

/// A history's colours, parallel to its visits: none when no visit's colour is known, the mask
/// only when some visit's is not.
fn write_visit_colours<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    visits: &[FruitVisit],
) -> ColourVectors<'a> {
    if visits.iter().all(|v| v.colour.is_none()) {
        return (None, None);
    }
    let colours: Vec<fb::Rgb> = visits
        .iter()
        .map(|v| rgb_to_fb(&v.colour.unwrap_or_default()))
        .collect();
    let colours = fbb.create_vector(&colours);
    let known: Vec<bool> = visits.iter().map(|v| v.colour.is_some()).collect();
    let known = known.contains(&false).then(|| fbb.create_vector(&known));
    (Some(colours), known)
}

/// Each visit's colour of a history of `visits` records: the colours, when present, must be one
/// per visit, and so must the mask.
fn read_visit_colours(
    kind: MessageKind,
    h: &fb::FruitHistory<'_>,
    visits: usize,
) -> Result<Vec<Option<Rgb>>> {
    let Some(colours) = h.colours().filter(|c| !c.is_empty()) else {
        return Ok(vec![None; visits]);
    };
    let known = h.colour_known().filter(|k| !k.is_empty());
    let known_len = known.map_or(colours.len(), |k| k.len());
    if colours.len() != visits || known_len != visits {
        return Err(content(
            kind,
            format!(
                "a fruit history of {visits} visits holds {} colours",
                colours.len()
            ),
        ));
    }
    let is_known = |i: usize| known.is_none_or(|k| k.get(i));
    let read = colours.iter().enumerate();
    Ok(read
        .map(|(i, c)| is_known(i).then(|| rgb_from_fb(c)))
        .collect())
}

/// Each visit's measured volume ratio of a history of `visits` records: when present, one per
/// visit, each positive or NaN (not measured).
fn read_volume_ratios(
    kind: MessageKind,
    h: &fb::FruitHistory<'_>,
    visits: usize,
) -> Result<Vec<Option<f64>>> {
    let Some(ratios) = h.volume_ratios().filter(|r| !r.is_empty()) else {
        return Ok(vec![None; visits]);
    };
    if ratios.len() != visits {
        let n = ratios.len();
        let why = format!("a fruit history of {visits} visits holds {n} volume ratios");
        return Err(content(kind, why));
    }
    ratios
        .iter()
        .map(|r| match f64::from(r) {
            r if r.is_nan() => Ok(None),
            r if r.is_finite() && r > 0.0 => Ok(Some(r)),
            _ => Err(content(kind, "fruit history holds a volume ratio that is not positive")),
        })
        .collect()
}

/// A history's last solid and surface: both or neither, every value finite.
fn read_last_surface(kind: MessageKind, h: &fb::FruitHistory<'_>) -> Result<Option<FruitSurface>> {
    let (solid, points) = match (h.last_solid(), h.last_surface()) {
        (None, None) => return Ok(None),
        (Some(solid), Some(points)) => (read_solid(kind, solid)?, points),
        _ => return Err(content(kind, "fruit history holds a last solid without its surface")),
    };
    let points_m: Vec<Point3<f64>> = points.iter().map(point).collect();
    let finite = points_m.iter().flat_map(|p| p.iter()).all(|v| v.is_finite())
        && solid_is_finite(&solid);
    match finite {
        true => Ok(Some(FruitSurface { solid, points_m })),
        false => Err(content(kind, "fruit history's last surface holds a non-finite value")),
    }
}

fn solid_is_finite(s: &FruitSolid) -> bool {
    let values = [s.volume_m3, s.taper, s.exponents[0], s.exponents[1]];
    s.centre.iter().chain(s.semi_axes_m.iter()).chain(values.iter()).all(|v| v.is_finite())
}

pub(super) fn rgb_to_fb(c: &Rgb) -> fb::Rgb {
    fb::Rgb::new(c.r, c.g, c.b)
}

pub(super) fn rgb_from_fb(c: &fb::Rgb) -> Rgb {
    Rgb::new(c.r(), c.g(), c.b())
}

/// Reads fruit histories; a record with a non-finite value, or colours that are not one per
/// visit, are an error.
pub(super) fn read_histories(
    kind: MessageKind,
    histories: Option<HistoryVector<'_>>,
) -> Result<Vec<FruitHistory>> {
    let Some(histories) = histories else {
        return Ok(Vec::new());
    };
    histories
        .iter()
        .map(|h| {
            let visits = h.visits().map(|vs| vs.iter().collect::<Vec<_>>());
            let visits = visits.unwrap_or_default();
            let colours = read_visit_colours(kind, &h, visits.len())?;
            let ratios = read_volume_ratios(kind, &h, visits.len())?;
            let visits = visits.into_iter().zip(colours).zip(ratios);
            let visits = visits.map(|((v, colour), volume_ratio)| {
                let record = FruitVisit {
                    visit: v.visit(),
                    centre: point(v.centre()),
                    size_m: vector(v.size()),
                    volume_m3: v.volume_m3().into(),
                    colour,
                    volume_ratio,
                };
                let finite = record
                    .centre
                    .iter()
                    .chain(record.size_m.iter())
                    .all(|x| x.is_finite())
                    && record.volume_m3.is_finite();
                match finite {
                    true => Ok(record),
                    false => Err(content(kind, "fruit history holds a non-finite value")),
                }
            });
            Ok(FruitHistory {
                season_id: h.season_id(),
                fruit_id: h.fruit_id(),
                visits: visits.collect::<Result<Vec<_>>>()?,
                last_surface: read_last_surface(kind, &h)?,
            })
        })
        .collect()
}

impl Wire for FruitEstimates {
    const KIND: MessageKind = MessageKind::FruitEstimates;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let fruits: Vec<_> = self.fruits.iter().map(|f| write_fruit(fbb, f)).collect();
        let fruits = fbb.create_vector(&fruits);
        let planner = fbb.create_string(&self.planner_id);
        let history = write_histories(fbb, &self.history);
        fb::FruitEstimates::create(
            fbb,
            &fb::FruitEstimatesArgs {
                fruits: Some(fruits),
                based_on_seq: self.based_on_seq,
                planner_id: Some(planner),
                owner_epoch: self.owner_epoch,
                visit: self.visit,
                history: Some(history),
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_fruit_estimates())?;
        let fruits = m
            .fruits()
            .map(|fs| {
                fs.iter()
                    .map(|f| read_fruit(Self::KIND, f))
                    .collect::<Result<Vec<_>>>()
            })
            .transpose()?
            .unwrap_or_default();
        Ok(FruitEstimates {
            fruits,
            based_on_seq: m.based_on_seq(),
            planner_id: string_or_empty(m.planner_id()),
            owner_epoch: m.owner_epoch(),
            visit: m.visit(),
            history: read_histories(Self::KIND, m.history())?,
        })
    }
}

fn vec3(v: &Vector3<f64>) -> fb::Vec3 {
    fb::Vec3::new(v.x as f32, v.y as f32, v.z as f32)
}

fn point(v: &fb::Vec3) -> Point3<f64> {
    Point3::new(v.x().into(), v.y().into(), v.z().into())
}

fn vector(v: &fb::Vec3) -> Vector3<f64> {
    point(v).coords
}

/// Writes one fruit: the one conversion of [`FruitEstimate`] to the wire.
pub(super) fn write_fruit<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    f: &FruitEstimate,
) -> WIPOffset<fb::Fruit<'a>> {
    let centre = vec3(&f.centre.coords);
    let bbox = fb::Box3::new(&vec3(&f.min.coords), &vec3(&f.max.coords));
    let fitted = f.solid.as_ref().map(|s| write_solid(fbb, s));
    let colour = f.colour.as_ref().map(rgb_to_fb);
    fb::Fruit::create(
        fbb,
        &fb::FruitArgs {
            id: f.id,
            centre: Some(&centre),
            box_: Some(&bbox),
            volume_m3: f.volume_m3 as f32,
            voxel_count: f.voxel_count.min(u32::MAX as usize) as u32,
            confidence: f.confidence as f32,
            fitted,
            view_directions: f.view_directions,
            colour: colour.as_ref(),
        },
    )
}

/// Writes a fitted solid.
fn write_solid<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    s: &FruitSolid,
) -> WIPOffset<fb::FittedEllipsoid<'a>> {
    let centre = vec3(&s.centre.coords);
    let semi_axes = vec3(&((s.box_max - s.box_min) / 2.0));
    let solid_box = fb::Box3::new(&vec3(&s.box_min.coords), &vec3(&s.box_max.coords));
    let body_semi_axes = vec3(&s.semi_axes_m);
    let q = s.world_from_body.quaternion();
    let rotation = fb::Quat::new(q.i, q.j, q.k, q.w);
    fb::FittedEllipsoid::create(
        fbb,
        &fb::FittedEllipsoidArgs {
            centre: Some(&centre),
            semi_axes: Some(&semi_axes),
            volume_m3: s.volume_m3 as f32,
            box_volume_m3: s.box_volume_m3 as f32,
            confidence: s.confidence as f32,
            is_fit: s.kind == SolidKind::Ellipsoid,
            box_: Some(&solid_box),
            body_semi_axes: Some(&body_semi_axes),
            world_from_body: Some(&rotation),
            exponent_profile: s.exponents[0] as f32,
            exponent_section: s.exponents[1] as f32,
            taper: s.taper as f32,
            rms_residual_m: s.rms_residual_m as f32,
        },
    )
}

/// Reads a fitted solid. A message from before the solid's own fields carries an axis-aligned
/// ellipsoid: centred at `centre`, with `semi_axes` for body semi-axes and box.
fn read_solid(kind: MessageKind, e: fb::FittedEllipsoid<'_>) -> Result<FruitSolid> {
    let centre = point(
        e.centre()
            .ok_or_else(|| content(kind, "fitted solid centre is missing"))?,
    );
    let half = vector(
        e.semi_axes()
            .ok_or_else(|| content(kind, "fitted solid semi-axes are missing"))?,
    );
    let (box_min, box_max) = match e.box_() {
        Some(b) => (point(b.min()), point(b.max())),
        None => (centre - half, centre + half),
    };
    let world_from_body = match e.world_from_body() {
        None => UnitQuaternion::identity(),
        Some(r) => {
            let q = Quaternion::new(r.w(), r.x(), r.y(), r.z());
            if !q.coords.iter().all(|v| v.is_finite()) || q.norm() < 1e-6 {
                return Err(content(kind, "fitted solid rotation is not a rotation"));
            }
            unit_rotation(q)
        }
    };
    Ok(FruitSolid {
        kind: if e.is_fit() {
            SolidKind::Ellipsoid
        } else {
            SolidKind::Box
        },
        centre,
        semi_axes_m: e.body_semi_axes().map_or(half, vector),
        world_from_body,
        exponents: [e.exponent_profile().into(), e.exponent_section().into()],
        taper: e.taper().into(),
        volume_m3: e.volume_m3().into(),
        box_min,
        box_max,
        box_volume_m3: e.box_volume_m3().into(),
        confidence: e.confidence().into(),
        rms_residual_m: e.rms_residual_m().into(),
    })
}

/// Reads one fruit, the one conversion of the wire to [`FruitEstimate`]; `kind` is the message
/// it sits in, for error reports.
pub(super) fn read_fruit(kind: MessageKind, f: fb::Fruit<'_>) -> Result<FruitEstimate> {
    let centre = f
        .centre()
        .ok_or_else(|| content(kind, "fruit centre is missing"))?;
    let bbox = f
        .box_()
        .ok_or_else(|| content(kind, "fruit box is missing"))?;
    let solid = f.fitted().map(|e| read_solid(kind, e)).transpose()?;
    Ok(FruitEstimate {
        id: f.id(),
        centre: point(centre),
        min: point(bbox.min()),
        max: point(bbox.max()),
        volume_m3: f.volume_m3().into(),
        voxel_count: f.voxel_count() as usize,
        confidence: f.confidence().into(),
        view_directions: f.view_directions(),
        solid,
        colour: f.colour().map(rgb_from_fb),
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::{decode_typed, encode, samples, Message};

    /// A planner from before the solid's rotation, exponents, taper, box and residual, the
    /// fruit's view directions and colours: it wrote only the first fields of each table (and
    /// histories without colours).
    #[derive(Clone, Debug)]
    struct OldSender(FruitEstimates);

    impl From<OldSender> for Message {
        fn from(old: OldSender) -> Self {
            Message::FruitEstimates(old.0)
        }
    }

    impl Wire for OldSender {
        const KIND: MessageKind = MessageKind::FruitEstimates;

        fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
            let m = &self.0;
            let fruits: Vec<_> = m
                .fruits
                .iter()
                .map(|f| {
                    let fitted = f.solid.as_ref().map(|s| {
                        let centre = vec3(&s.centre.coords);
                        let semi_axes = vec3(&((s.box_max - s.box_min) / 2.0));
                        let mut t = fb::FittedEllipsoidBuilder::new(fbb);
                        t.add_centre(&centre);
                        t.add_semi_axes(&semi_axes);
                        t.add_volume_m3(s.volume_m3 as f32);
                        t.add_box_volume_m3(s.box_volume_m3 as f32);
                        t.add_confidence(s.confidence as f32);
                        t.add_is_fit(s.kind == SolidKind::Ellipsoid);
                        t.finish()
                    });
                    let centre = vec3(&f.centre.coords);
                    let bbox = fb::Box3::new(&vec3(&f.min.coords), &vec3(&f.max.coords));
                    let mut t = fb::FruitBuilder::new(fbb);
                    t.add_id(f.id);
                    t.add_centre(&centre);
                    t.add_box_(&bbox);
                    t.add_volume_m3(f.volume_m3 as f32);
                    t.add_voxel_count(f.voxel_count as u32);
                    t.add_confidence(f.confidence as f32);
                    if let Some(fitted) = fitted {
                        t.add_fitted(fitted);
                    }
                    t.finish()
                })
                .collect();
            let fruits = fbb.create_vector(&fruits);
            let planner = fbb.create_string(&m.planner_id);
            let history = old_histories(fbb, &m.history);
            let mut t = fb::FruitEstimatesBuilder::new(fbb);
            t.add_fruits(fruits);
            t.add_based_on_seq(m.based_on_seq);
            t.add_planner_id(planner);
            t.add_history(history);
            t.finish().as_union_value()
        }

        fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
            FruitEstimates::read_payload(envelope).map(OldSender)
        }
    }

    /// Histories as a planner from before the colours wrote them: `visits` and no more.
    fn old_histories<'a>(
        fbb: &mut FlatBufferBuilder<'a>,
        histories: &[FruitHistory],
    ) -> WIPOffset<HistoryVector<'a>> {
        let tables: Vec<_> = histories
            .iter()
            .map(|h| {
                let visits = fb_visits(&h.visits);
                let visits = fbb.create_vector(&visits);
                let mut t = fb::FruitHistoryBuilder::new(fbb);
                t.add_season_id(h.season_id);
                t.add_fruit_id(h.fruit_id);
                t.add_visits(visits);
                t.finish()
            })
            .collect();
        fbb.create_vector(&tables)
    }

    fn round_trip(m: &FruitEstimates) -> FruitEstimates {
        decode_typed::<FruitEstimates>(&encode(&samples::header(3), m))
            .unwrap()
            .1
    }

    #[test]
    fn the_solid_round_trips_with_its_rotation_exponents_and_taper() {
        let sample = samples::fruit_estimates();
        let read = round_trip(&sample);
        assert_eq!(format!("{read:?}"), format!("{sample:?}"));
        let solid = read.fruits[0].solid.unwrap();
        assert!(solid.world_from_body.angle() > 0.1);
        assert_eq!(solid.exponents, [0.5, 1.0]);
        assert_eq!(read.fruits[0].view_directions, 3);
    }

    #[test]
    fn fruits_from_a_sender_without_the_solid_fields_read_as_axis_aligned_ellipsoids() {
        let sample = samples::fruit_estimates();
        let old = encode(&samples::header(3), &OldSender(sample.clone()));
        let (_, read) = decode_typed::<FruitEstimates>(&old).unwrap();
        let (f, was) = (&read.fruits[0], &sample.fruits[0]);
        assert_eq!(
            (f.id, f.centre, f.min, f.max),
            (was.id, was.centre, was.min, was.max)
        );
        assert_eq!(
            (f.voxel_count, f.confidence),
            (was.voxel_count, was.confidence)
        );
        assert_eq!(f.view_directions, 0);
        assert_eq!((f.colour, was.colour.is_some()), (None, true));
        // The histories read whole, every visit's colour unknown.
        assert_eq!(read.history.len(), sample.history.len());
        for (h, h_was) in read.history.iter().zip(&sample.history) {
            assert_eq!(
                (h.season_id, h.visits.len()),
                (h_was.season_id, h_was.visits.len())
            );
            assert!(h.visits.iter().all(|v| v.colour.is_none()), "{h:?}");
            assert!(h_was.visits.iter().all(|v| v.colour.is_some()));
        }
        let (s, s_was) = (f.solid.unwrap(), was.solid.unwrap());
        let half = (s_was.box_max - s_was.box_min) / 2.0;
        assert_eq!(s.kind, SolidKind::Ellipsoid);
        assert_eq!(s.centre, s_was.centre);
        assert_eq!(s.semi_axes_m, half);
        assert_eq!((s.box_min, s.box_max), (s.centre - half, s.centre + half));
        assert_eq!(s.world_from_body, UnitQuaternion::identity());
        assert_eq!((s.exponents, s.taper), ([1.0, 1.0], 0.0));
        assert_eq!(
            (s.volume_m3, s.confidence),
            (s_was.volume_m3, s_was.confidence)
        );
        assert!(s.rms_residual_m.is_nan());
    }
}

#[cfg(test)]
mod colour_tests {
    #![allow(clippy::unwrap_used)]

    use super::*;
    use crate::{decode_typed, encode, samples, ProtoError};

    #[test]
    fn the_fruits_colour_and_each_visits_round_trip() {
        let sample = samples::fruit_estimates();
        let read = decode_typed::<FruitEstimates>(&encode(&samples::header(3), &sample))
            .unwrap()
            .1;
        assert_eq!(read.fruits[0].colour, Some(Rgb::new(190, 35, 25)));
        let colours: Vec<_> = read.history[0].visits.iter().map(|v| v.colour).collect();
        assert_eq!(
            colours,
            [Some(Rgb::new(110, 150, 40)), Some(Rgb::new(190, 35, 25))]
        );
        assert_eq!(read, sample);
    }

    #[test]
    fn a_history_with_some_visits_colour_unknown_keeps_which() {
        let mut sample = samples::fruit_estimates();
        sample.history[0].visits[0].colour = None;
        let read = decode_typed::<FruitEstimates>(&encode(&samples::header(3), &sample))
            .unwrap()
            .1;
        assert_eq!(read.history, sample.history);
        // Every colour unknown: nothing written, none read.
        sample.history[0].visits[1].colour = None;
        let read = decode_typed::<FruitEstimates>(&encode(&samples::header(3), &sample))
            .unwrap()
            .1;
        assert_eq!(read.history, sample.history);
    }

    /// A sender whose one history has two visits and one colour.
    /// A sender whose one history of two visits is broken one way.
    #[derive(Clone, Debug)]
    enum BrokenSender {
        OneColour,
        OneVolumeRatio,
        NegativeVolumeRatio,
        SolidWithoutSurface,
    }

    impl From<BrokenSender> for crate::Message {
        fn from(_: BrokenSender) -> Self {
            crate::Message::FruitEstimates(samples::fruit_estimates())
        }
    }

    impl Wire for BrokenSender {
        const KIND: MessageKind = MessageKind::FruitEstimates;

        fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
            let v = fb::Vec3::new(0.1, 0.2, 0.3);
            let visits = fbb.create_vector(&[
                fb::FruitVisit::new(0, &v, &v, 1e-4),
                fb::FruitVisit::new(1, &v, &v, 2e-4),
            ]);
            let mut args = fb::FruitHistoryArgs {
                season_id: 1,
                fruit_id: 0,
                visits: Some(visits),
                ..Default::default()
            };
            match self {
                Self::OneColour => {
                    args.colours = Some(fbb.create_vector(&[fb::Rgb::new(200, 30, 20)]));
                }
                Self::OneVolumeRatio => args.volume_ratios = Some(fbb.create_vector(&[1.5f32])),
                Self::NegativeVolumeRatio => {
                    args.volume_ratios = Some(fbb.create_vector(&[f32::NAN, -1.5]));
                }
                Self::SolidWithoutSurface => {
                    let solid = samples::fruit_estimates().fruits[0].solid;
                    args.last_solid = solid.map(|s| write_solid(fbb, &s));
                }
            }
            let history = fb::FruitHistory::create(fbb, &args);
            let history = fbb.create_vector(&[history]);
            let mut t = fb::FruitEstimatesBuilder::new(fbb);
            t.add_history(history);
            t.finish().as_union_value()
        }

        fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
            FruitEstimates::read_payload(envelope).map(|_| BrokenSender::OneColour)
        }
    }

    #[test]
    fn volume_ratios_and_last_surfaces_that_do_not_fit_their_history_are_content_errors() {
        for (broken, why) in [
            (BrokenSender::OneVolumeRatio, "2 visits holds 1 volume ratios"),
            (BrokenSender::NegativeVolumeRatio, "not positive"),
            (BrokenSender::SolidWithoutSurface, "last solid without its surface"),
        ] {
            let bytes = encode(&samples::header(3), &broken);
            let err = decode_typed::<FruitEstimates>(&bytes).unwrap_err();
            assert!(matches!(err, ProtoError::Content { .. }), "{err}");
            assert!(err.to_string().contains(why), "{err}");
        }
    }

    #[test]
    fn colours_that_are_not_one_per_visit_are_a_content_error() {
        let bytes = encode(&samples::header(3), &BrokenSender::OneColour);
        let err = decode_typed::<FruitEstimates>(&bytes).unwrap_err();
        assert!(matches!(err, ProtoError::Content { .. }), "{err}");
        assert!(
            err.to_string().contains("2 visits holds 1 colours"),
            "{err}"
        );
    }
}
