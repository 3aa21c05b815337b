//! Weights messages: the envelope and network checks never panic, and the safetensors payload
//! parser (the next step an actor takes) never panics on what passes them.
#![no_main]

use crawler_proto::validate;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(weights) = validate::weights(data, "fuzz") {
        let spec = weights.network.expect("validated weights name their network");
        assert!(spec.obs_dim > 0 && spec.num_actions > 0);
        let _ = safetensors::SafeTensors::deserialize(&weights.safetensors);
    }
    // The payload parser on its own, on raw bytes.
    let _ = safetensors::SafeTensors::deserialize(data);
});
