//! FleetFruits: every trolley's fruits merged into one map, planner → dashboard.

use flatbuffers::{FlatBufferBuilder, UnionWIPOffset, WIPOffset};

use super::convert::{content, payload, string_or_empty, strings, strings_from_fb};
use super::fruit_estimates::{read_fruit, write_fruit};
use glasshouse_geom::FruitEstimate;

use crate::{fb, MessageKind, Result, Wire};

/// One fruit of the fleet map: the one fruit estimate kept (the most confident source's) with
/// its fleet id and the `"{trolley}/{fruit id}"` of every estimate merged into it.
#[derive(Clone, Debug, PartialEq)]
pub struct FleetFruit {
    pub fleet_id: String,
    pub fruit: FruitEstimate,
    pub sources: Vec<String>,
}

/// Every trolley's fruits merged into one map.
#[derive(Clone, Debug, PartialEq)]
pub struct FleetFruits {
    pub fruits: Vec<FleetFruit>,
    pub planner_id: String,
    pub trolleys: u32,
}

fn write_fleet_fruit<'a>(
    fbb: &mut FlatBufferBuilder<'a>,
    f: &FleetFruit,
) -> WIPOffset<fb::FleetFruit<'a>> {
    let fleet_id = fbb.create_string(&f.fleet_id);
    let fruit = write_fruit(fbb, &f.fruit);
    let sources = strings(fbb, &f.sources);
    fb::FleetFruit::create(
        fbb,
        &fb::FleetFruitArgs {
            fleet_id: Some(fleet_id),
            fruit: Some(fruit),
            sources: Some(sources),
        },
    )
}

fn read_fleet_fruit(f: fb::FleetFruit<'_>) -> Result<FleetFruit> {
    let kind = MessageKind::FleetFruits;
    let fruit = f
        .fruit()
        .ok_or_else(|| content(kind, "fleet fruit without its estimate"))?;
    Ok(FleetFruit {
        fleet_id: string_or_empty(f.fleet_id()),
        fruit: read_fruit(kind, fruit)?,
        sources: strings_from_fb(f.sources()),
    })
}

impl Wire for FleetFruits {
    const KIND: MessageKind = MessageKind::FleetFruits;

    fn write_payload(&self, fbb: &mut FlatBufferBuilder<'_>) -> WIPOffset<UnionWIPOffset> {
        let fruits: Vec<_> = self
            .fruits
            .iter()
            .map(|f| write_fleet_fruit(fbb, f))
            .collect();
        let fruits = fbb.create_vector(&fruits);
        let planner = fbb.create_string(&self.planner_id);
        fb::FleetFruits::create(
            fbb,
            &fb::FleetFruitsArgs {
                fruits: Some(fruits),
                planner_id: Some(planner),
                trolleys: self.trolleys,
            },
        )
        .as_union_value()
    }

    fn read_payload(envelope: &fb::Envelope<'_>) -> Result<Self> {
        let m = payload(envelope.payload_as_fleet_fruits())?;
        let fruits = m
            .fruits()
            .map(|fs| fs.iter().map(read_fleet_fruit).collect::<Result<Vec<_>>>())
            .transpose()?
            .unwrap_or_default();
        Ok(FleetFruits {
            fruits,
            planner_id: string_or_empty(m.planner_id()),
            trolleys: m.trolleys(),
        })
    }
}
