//! Episode stats, actor status, insert credits, control and run info: decoding and validation never panic.
#![no_main]

use crawler_proto::validate;
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(stats) = validate::episode_stats(data, "fuzz") {
        assert!(stats.speed.is_finite() && stats.distance.is_finite() && stats.episode_return.is_finite());
    }
    let _ = validate::actor_status(data, "fuzz");
    let _ = validate::insert_credit(data, "fuzz", "crawler/fuzz/credit/0");
    let _ = validate::control(data, "fuzz");
    let _ = validate::run_info(data);
});
