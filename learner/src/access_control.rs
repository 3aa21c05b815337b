//! The zenoh access-control policy of the learner's router, for runs served over mutual TLS.
//!
//! Remote processes are told apart by the common name (CN) of their client certificate:
//! every actor certificate carries [`ACTOR_COMMON_NAME`], read-only monitors carry
//! [`OBSERVER_COMMON_NAME`] (`deploy/make-tls.sh` issues both). Everything not allowed below is
//! denied, for these subjects and for any other certificate the CA signed. The learner's own
//! publications (weights, control) come from its in-process session, which no ACL rule sees:
//! only the remote faces of the router are filtered. So:
//!
//! - actors may put transitions, stats and status of this run, subscribe to its weights and
//!   control, query run info and weights, and declare their liveliness token;
//! - only the learner publishes weights and control: no remote subject may put on those keys,
//!   so forged weights or a forged stop reach nobody;
//! - observers may subscribe to and query anything of this run, and put nothing.
//!
//! zenoh drops denied messages silently (no error reaches the sender), which is why the
//! security tests check what actually arrives (`tests/tests/security.rs`).

use crawler_proto::keys;
use serde_json::{Value, json};

/// The CN of every actor (and evaluator) certificate.
pub const ACTOR_COMMON_NAME: &str = "crawler-actor";
/// The CN of read-only monitor certificates (dashboards, the security tests' probe).
pub const OBSERVER_COMMON_NAME: &str = "crawler-observer";

/// The `access_control` section of the router's zenoh config for run `run`.
pub fn policy(run: &str) -> Value {
    let transitions = keys::all_transitions(run);
    let stats = keys::all_stats(run);
    let status = keys::all_status(run);
    let weights = keys::weights(run);
    let control = keys::control(run);
    let info = keys::info(run);
    // Actors that were not told their run ask `crawler/*/info`; the ACL allows a query only
    // when a rule's key includes the query's, so discovery needs the wildcard form.
    let any_info = keys::info("*");
    let actor_tokens = keys::all_alive_actors(run);
    let whole_run = format!("{}/{run}/**", keys::ROOT);

    let rule = |id: &str, flow: &str, messages: &[&str], key_exprs: &[&str]| {
        json!({
            "id": id,
            "permission": "allow",
            "flows": [flow],
            "messages": messages,
            "key_exprs": key_exprs,
        })
    };
    let rules = vec![
        rule("actor-publishes", "ingress", &["put"], &[&transitions, &stats, &status]),
        rule("actor-subscribes", "ingress", &["declare_subscriber"], &[&weights, &control]),
        rule("actor-receives", "egress", &["put"], &[&weights, &control]),
        rule("actor-queries", "ingress", &["query"], &[&any_info, &weights]),
        rule("actor-gets-replies", "egress", &["reply"], &[&info, &weights]),
        rule("actor-liveliness", "ingress", &["liveliness_token"], &[&actor_tokens]),
        // The learner's subscribers, queryables and liveliness token, announced to remote
        // sessions: a client's publisher sends only where it knows of a matching subscriber.
        rule(
            "learner-declarations-reach-remotes",
            "egress",
            &["declare_subscriber", "declare_queryable", "liveliness_token"],
            &[&whole_run],
        ),
        rule(
            "observer-subscribes",
            "ingress",
            &["declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query"],
            &[&whole_run, &any_info],
        ),
        rule("observer-receives", "egress", &["put", "delete", "reply"], &[&whole_run]),
    ];
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [
            { "id": "actors", "cert_common_names": [ACTOR_COMMON_NAME] },
            { "id": "observers", "cert_common_names": [OBSERVER_COMMON_NAME] },
        ],
        "policies": [
            {
                "id": "actors",
                "subjects": ["actors"],
                "rules": [
                    "actor-publishes", "actor-subscribes", "actor-receives", "actor-queries",
                    "actor-gets-replies", "actor-liveliness", "learner-declarations-reach-remotes",
                ],
            },
            {
                "id": "observers",
                "subjects": ["observers"],
                "rules": ["observer-subscribes", "observer-receives", "learner-declarations-reach-remotes"],
            },
        ],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rules_for(policy: &Value, subject: &str) -> Vec<Value> {
        let names: Vec<&str> = policy["policies"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|p| p["subjects"].as_array().unwrap().iter().any(|s| s == subject))
            .flat_map(|p| p["rules"].as_array().unwrap().iter().map(|r| r.as_str().unwrap()))
            .collect();
        policy["rules"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|r| names.contains(&r["id"].as_str().unwrap()))
            .cloned()
            .collect()
    }

    fn allows(rules: &[Value], flow: &str, message: &str, key: &str) -> bool {
        rules.iter().any(|r| {
            r["flows"].as_array().unwrap().iter().any(|f| f == flow)
                && r["messages"].as_array().unwrap().iter().any(|m| m == message)
                && r["key_exprs"].as_array().unwrap().iter().any(|k| k == key)
        })
    }

    #[test]
    fn zenoh_accepts_the_policy() {
        let mut config = zenoh::Config::default();
        config.insert_json5("access_control", &policy("run-1").to_string()).unwrap();
    }

    #[test]
    fn no_remote_subject_may_put_weights_or_control() {
        let policy = policy("r");
        for subject in ["actors", "observers"] {
            let rules = rules_for(&policy, subject);
            for key in [keys::weights("r"), keys::control("r"), format!("{}/r/**", keys::ROOT)] {
                assert!(!allows(&rules, "ingress", "put", &key), "{subject} may put {key}");
            }
        }
        assert_eq!(policy["default_permission"], "deny");
    }

    #[test]
    fn actors_may_do_what_the_actor_loop_does() {
        let rules = rules_for(&policy("r"), "actors");
        assert!(allows(&rules, "ingress", "put", &keys::all_transitions("r")));
        assert!(allows(&rules, "ingress", "put", &keys::all_stats("r")));
        assert!(allows(&rules, "ingress", "declare_subscriber", &keys::weights("r")));
        assert!(allows(&rules, "egress", "put", &keys::weights("r")));
        assert!(allows(&rules, "ingress", "query", &keys::info("*")));
        assert!(allows(&rules, "ingress", "liveliness_token", &keys::all_alive_actors("r")));
        // Not another run's topics.
        assert!(!allows(&rules, "ingress", "put", &keys::all_transitions("other")));
    }
}
