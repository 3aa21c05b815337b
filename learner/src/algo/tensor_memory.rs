//! A libtorch tensor's elements borrowed as a Rust slice, for the two loops of an update that
//! touch every parameter: the gradient norm and the fused Adam step.
//!
//! Why: through tch's safe API, each of those loops costs copies of the whole network (join
//! the gradients with `cat`, copy them out, copy the parameters out, build a tensor from the
//! result, copy it back): five extra passes over 760 KB for the study's network, about a
//! fifth of a batch-32 update. Reading and writing the storage in place needs no copy.

use tch::{Device, Kind, Tensor};

/// Panics unless `tensor` is a contiguous f32 CPU tensor: the layout a slice can describe.
/// Every tensor passed here is one the learner made itself, so a failure is a programming
/// error.
fn assert_plain_f32(tensor: &Tensor) {
    assert!(
        tensor.kind() == Kind::Float && tensor.device() == Device::Cpu && tensor.is_contiguous(),
        "tensor_memory needs a contiguous f32 CPU tensor, got {:?} on {:?}",
        tensor.kind(),
        tensor.device()
    );
}

/// `tensor` as a contiguous f32 CPU tensor outside autograd: itself (a shallow clone) when it
/// already is one, else a converted copy. At batch 32 an update is short enough that three
/// dispatcher calls per tensor (`detach`, `to_kind`, `contiguous`) for tensors that need none
/// of them showed in its profile.
pub fn plain_f32(tensor: &Tensor) -> Tensor {
    let plain = tensor.kind() == Kind::Float
        && tensor.device() == Device::Cpu
        && tensor.is_contiguous()
        && !tensor.requires_grad();
    if plain { tensor.shallow_clone() } else { tensor.detach().to_kind(Kind::Float).contiguous() }
}

/// The elements of `tensor`, read in place.
///
/// # Safety
/// While the slice lives, nothing may write this tensor's storage through any handle (views
/// and shallow clones share it), and libtorch may not free or resize it.
#[allow(unsafe_code)]
pub unsafe fn f32s(tensor: &Tensor) -> &[f32] {
    assert_plain_f32(tensor);
    let len = tensor.numel();
    if len == 0 {
        return &[];
    }
    // SAFETY: the tensor is a contiguous f32 CPU tensor of `len` elements, so its data pointer
    // (which includes the storage offset) addresses `len` initialised, aligned f32s; the
    // caller guarantees no writer while the borrow of `tensor` lasts.
    unsafe { std::slice::from_raw_parts(tensor.data_ptr().cast::<f32>(), len) }
}

/// The elements of `tensor`, written in place.
///
/// # Safety
/// While the slice lives, nothing may read or write this tensor's storage through any other
/// handle (views and shallow clones share it), and libtorch may not free or resize it.
#[allow(unsafe_code)]
pub unsafe fn f32s_mut(tensor: &mut Tensor) -> &mut [f32] {
    assert_plain_f32(tensor);
    let len = tensor.numel();
    if len == 0 {
        return &mut [];
    }
    // SAFETY: as in `f32s`; the caller guarantees that this slice is the only access to the
    // storage while the mutable borrow of `tensor` lasts.
    unsafe { std::slice::from_raw_parts_mut(tensor.data_ptr().cast::<f32>(), len) }
}
