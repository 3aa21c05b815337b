//! The protobuf encoding of [`TransitionBatch`], written out rather than derived.
//!
//! Why: prost decodes a packed `repeated float` one value at a time (a closure call, a width
//! check and a push per float). Transition batches are 80 floats per transition, and at a few
//! million transitions a second that loop was the receive side's largest cost. Here a packed
//! float field that lies whole in the buffer's current chunk is copied in one pass that the
//! compiler vectorises; every other case (a field split across chunks, a length that is not
//! a whole number of floats, unpacked values, an underflow) goes to prost's own decoder, so
//! prost defines the errors and edge cases. Everything else delegates to prost's encoding
//! functions field by field, in tag order, as its derive does.
//!
//! `prost::encoding` is the module prost's derive expands to; it is hidden from prost's docs
//! but versioned with the crate, which the workspace pins to one minor version.

use prost::bytes::{Buf, BufMut};
use prost::encoding::{
    DecodeContext, WireType, bool as pbool, decode_varint, float, skip_field, string, uint32, uint64,
};
use prost::{DecodeError, Message};

use crate::TransitionBatch;

const NAME: &str = "TransitionBatch";

/// Appends a packed float field's values to `values`: in one pass when the field lies whole
/// in `buf`'s current chunk and holds whole floats, by prost otherwise.
fn merge_floats(
    wire_type: WireType,
    values: &mut Vec<f32>,
    buf: &mut impl Buf,
    ctx: DecodeContext,
) -> Result<(), DecodeError> {
    if wire_type == WireType::LengthDelimited {
        let mut chunk = buf.chunk();
        let whole = chunk.len();
        if let Ok(len) = decode_varint(&mut chunk) {
            let prefix = whole - chunk.len();
            let fits = usize::try_from(len).ok().filter(|&len| len <= chunk.len() && len % 4 == 0);
            if let Some(len) = fits {
                values.reserve(len / 4);
                values.extend(chunk[..len].chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])));
                buf.advance(prefix + len);
                return Ok(());
            }
        }
    }
    float::merge_repeated(wire_type, values, buf, ctx)
}

/// Names the field in a decode error, as prost's derive does.
fn field(name: &'static str) -> impl FnOnce(DecodeError) -> DecodeError {
    move |mut error| {
        error.push(NAME, name);
        error
    }
}

impl Message for TransitionBatch {
    fn encode_raw(&self, buf: &mut impl BufMut) {
        if self.protocol_version != 0 {
            uint32::encode(1, &self.protocol_version, buf);
        }
        if !self.run_id.is_empty() {
            string::encode(2, &self.run_id, buf);
        }
        if self.actor_id != 0 {
            uint32::encode(3, &self.actor_id, buf);
        }
        if self.sequence != 0 {
            uint64::encode(4, &self.sequence, buf);
        }
        if self.incarnation != 0 {
            uint64::encode(5, &self.incarnation, buf);
        }
        if self.obs_dim != 0 {
            uint32::encode(6, &self.obs_dim, buf);
        }
        uint32::encode_packed(7, &self.env_ids, buf);
        float::encode_packed(8, &self.observations, buf);
        float::encode_packed(9, &self.next_observations, buf);
        uint32::encode_packed(10, &self.actions, buf);
        float::encode_packed(11, &self.rewards, buf);
        pbool::encode_packed(12, &self.terminated, buf);
        pbool::encode_packed(13, &self.truncated, buf);
        float::encode_packed(14, &self.priorities, buf);
        if self.weights_version != 0 {
            uint64::encode(15, &self.weights_version, buf);
        }
        if self.physics_steps != 0 {
            uint64::encode(16, &self.physics_steps, buf);
        }
        if self.count != 0 {
            uint32::encode(17, &self.count, buf);
        }
    }

    fn merge_field(
        &mut self,
        tag: u32,
        wire_type: WireType,
        buf: &mut impl Buf,
        ctx: DecodeContext,
    ) -> Result<(), DecodeError> {
        match tag {
            1 => uint32::merge(wire_type, &mut self.protocol_version, buf, ctx).map_err(field("protocol_version")),
            2 => string::merge(wire_type, &mut self.run_id, buf, ctx).map_err(field("run_id")),
            3 => uint32::merge(wire_type, &mut self.actor_id, buf, ctx).map_err(field("actor_id")),
            4 => uint64::merge(wire_type, &mut self.sequence, buf, ctx).map_err(field("sequence")),
            5 => uint64::merge(wire_type, &mut self.incarnation, buf, ctx).map_err(field("incarnation")),
            6 => uint32::merge(wire_type, &mut self.obs_dim, buf, ctx).map_err(field("obs_dim")),
            7 => uint32::merge_repeated(wire_type, &mut self.env_ids, buf, ctx).map_err(field("env_ids")),
            8 => merge_floats(wire_type, &mut self.observations, buf, ctx).map_err(field("observations")),
            9 => merge_floats(wire_type, &mut self.next_observations, buf, ctx).map_err(field("next_observations")),
            10 => uint32::merge_repeated(wire_type, &mut self.actions, buf, ctx).map_err(field("actions")),
            11 => merge_floats(wire_type, &mut self.rewards, buf, ctx).map_err(field("rewards")),
            12 => pbool::merge_repeated(wire_type, &mut self.terminated, buf, ctx).map_err(field("terminated")),
            13 => pbool::merge_repeated(wire_type, &mut self.truncated, buf, ctx).map_err(field("truncated")),
            14 => merge_floats(wire_type, &mut self.priorities, buf, ctx).map_err(field("priorities")),
            15 => uint64::merge(wire_type, &mut self.weights_version, buf, ctx).map_err(field("weights_version")),
            16 => uint64::merge(wire_type, &mut self.physics_steps, buf, ctx).map_err(field("physics_steps")),
            17 => uint32::merge(wire_type, &mut self.count, buf, ctx).map_err(field("count")),
            _ => skip_field(wire_type, tag, buf, ctx),
        }
    }

    fn encoded_len(&self) -> usize {
        let scalar32 = |tag: u32, value: u32| if value != 0 { uint32::encoded_len(tag, &value) } else { 0 };
        let scalar64 = |tag: u32, value: u64| if value != 0 { uint64::encoded_len(tag, &value) } else { 0 };
        scalar32(1, self.protocol_version)
            + if self.run_id.is_empty() { 0 } else { string::encoded_len(2, &self.run_id) }
            + scalar32(3, self.actor_id)
            + scalar64(4, self.sequence)
            + scalar64(5, self.incarnation)
            + scalar32(6, self.obs_dim)
            + uint32::encoded_len_packed(7, &self.env_ids)
            + float::encoded_len_packed(8, &self.observations)
            + float::encoded_len_packed(9, &self.next_observations)
            + uint32::encoded_len_packed(10, &self.actions)
            + float::encoded_len_packed(11, &self.rewards)
            + pbool::encoded_len_packed(12, &self.terminated)
            + pbool::encoded_len_packed(13, &self.truncated)
            + float::encoded_len_packed(14, &self.priorities)
            + scalar64(15, self.weights_version)
            + scalar64(16, self.physics_steps)
            + scalar32(17, self.count)
    }

    fn clear(&mut self) {
        self.protocol_version = 0;
        self.run_id.clear();
        self.actor_id = 0;
        self.sequence = 0;
        self.incarnation = 0;
        self.obs_dim = 0;
        self.env_ids.clear();
        self.observations.clear();
        self.next_observations.clear();
        self.actions.clear();
        self.rewards.clear();
        self.terminated.clear();
        self.truncated.clear();
        self.priorities.clear();
        self.weights_version = 0;
        self.physics_steps = 0;
        self.count = 0;
    }
}
