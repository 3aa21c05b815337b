//! The zenoh access-control policy of the learner's router. It is always on.
//!
//! Everything not allowed below is denied. The learner's own publications (weights, control,
//! insert credits) and queryables (run info, weights) come from its in-process session, which no ACL rule
//! sees: only the remote faces of the router are filtered. So:
//!
//! - actors may put transitions, stats and status of this run, subscribe to its weights,
//!   control and insert credits, query run info and weights, and declare their liveliness
//!   token;
//! - only the learner publishes weights, control and insert credits and serves the run's
//!   queryables: no remote session may put on those keys or declare a queryable, so forged
//!   weights, a forged stop, forged credit or a forged run info reach nobody;
//! - no remote session may subscribe to transitions: a subscriber that never reads would
//!   stall the actors' reliable, blocking publications (and so the learner's ingest).
//!
//! Who is an actor: under mutual TLS, a session whose client certificate carries
//! [`ACTOR_COMMON_NAME`]; read-only monitors carry [`OBSERVER_COMMON_NAME`] and may subscribe
//! to and query the run's weights, control, stats, status and liveliness, and put nothing
//! (`deploy/make-tls.sh` issues both); any other certificate the CA signed may do nothing.
//! Without TLS nothing tells sessions apart, so every remote session gets the actor's rights
//! and no more: plain TCP is for loopback and trusted networks (the learner refuses a plain
//! listener on any other address unless told `--allow-plain-remote`).
//!
//! zenoh drops denied messages silently (no error reaches the sender), which is why the
//! security tests check what actually arrives (`tests/tests/it/security.rs`).

use crawler_proto::keys;
use serde_json::{Value, json};

/// The CN of every actor (and evaluator) certificate.
pub const ACTOR_COMMON_NAME: &str = "crawler-actor";
/// The CN of read-only monitor certificates (dashboards, the security tests' probe).
pub const OBSERVER_COMMON_NAME: &str = "crawler-observer";

/// How remote sessions are identified.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Identity {
    /// Mutual TLS: roles by certificate common name.
    Certificates,
    /// Plain TCP: every remote session is an actor.
    None,
}

/// The `access_control` section of the router's zenoh config for run `run`.
///
/// Long on purpose: the policy is one JSON document (rules, subjects, policies), kept whole
/// so that it reads as zenoh's configuration reference describes it.
pub fn policy(run: &str, identity: Identity) -> Value {
    let transitions = keys::all_transitions(run);
    let stats = keys::all_stats(run);
    let status = keys::all_status(run);
    let weights = keys::weights(run);
    let control = keys::control(run);
    let credits = keys::all_credits(run);
    let info = keys::info(run);
    // Actors that were not told their run ask `crawler/*/info`; the ACL allows a query only
    // when a rule's key includes the query's, so discovery needs the wildcard form.
    let any_info = keys::info("*");
    let actor_tokens = keys::all_alive_actors(run);
    let evaluator_tokens = keys::all_alive_evaluators(run);
    let alive = format!("{}/{run}/alive/**", keys::ROOT);
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
        rule("actor-subscribes", "ingress", &["declare_subscriber"], &[&weights, &control, &credits]),
        rule("actor-receives", "egress", &["put"], &[&weights, &control, &credits]),
        rule("actor-queries", "ingress", &["query"], &[&any_info, &weights]),
        rule("actor-gets-replies", "egress", &["reply"], &[&info, &weights]),
        rule("actor-liveliness", "ingress", &["liveliness_token"], &[&actor_tokens, &evaluator_tokens]),
        // The learner's subscribers, queryables and liveliness token, announced to remote
        // sessions: a client's publisher sends only where it knows of a matching subscriber.
        rule(
            "learner-declarations-reach-remotes",
            "egress",
            &["declare_subscriber", "declare_queryable", "liveliness_token"],
            &[&whole_run],
        ),
        // Everything of the run but transitions: a stalled reader of those would block the
        // actors' reliable publications.
        rule("observer-subscribes", "ingress", &["declare_subscriber"], &[&weights, &control, &stats, &status]),
        rule("observer-queries", "ingress", &["query"], &[&any_info, &weights]),
        rule(
            "observer-watches-liveliness",
            "ingress",
            &["declare_liveliness_subscriber", "liveliness_query"],
            &[&alive],
        ),
        rule("observer-receives", "egress", &["put", "delete", "reply"], &[&weights, &control, &stats, &status, &info]),
        rule("observer-sees-liveliness", "egress", &["liveliness_token"], &[&alive]),
    ];
    let actor_rules = json!([
        "actor-publishes",
        "actor-subscribes",
        "actor-receives",
        "actor-queries",
        "actor-gets-replies",
        "actor-liveliness",
        "learner-declarations-reach-remotes",
    ]);
    let (subjects, policies) = match identity {
        Identity::Certificates => (
            json!([
                { "id": "actors", "cert_common_names": [ACTOR_COMMON_NAME] },
                { "id": "observers", "cert_common_names": [OBSERVER_COMMON_NAME] },
            ]),
            json!([
                { "id": "actors", "subjects": ["actors"], "rules": actor_rules },
                {
                    "id": "observers",
                    "subjects": ["observers"],
                    "rules": [
                        "observer-subscribes", "observer-queries", "observer-watches-liveliness",
                        "observer-receives", "observer-sees-liveliness", "learner-declarations-reach-remotes",
                    ],
                },
            ]),
        ),
        // A subject with no property matches every remote session.
        Identity::None => (
            json!([{ "id": "remote" }]),
            json!([{ "id": "remote-sessions-are-actors", "subjects": ["remote"], "rules": actor_rules }]),
        ),
    };
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
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

    /// Whether a rule covers `key` as zenoh decides it: the rule's key expression includes
    /// the message's (a query or declaration with a wildcard needs a rule that includes all of
    /// it). zenoh's own inclusion, not string equality.
    fn allows(rules: &[Value], flow: &str, message: &str, key: &str) -> bool {
        let key = zenoh::key_expr::KeyExpr::try_from(key).unwrap();
        rules.iter().any(|r| {
            r["flows"].as_array().unwrap().iter().any(|f| f == flow)
                && r["messages"].as_array().unwrap().iter().any(|m| m == message)
                && r["key_exprs"].as_array().unwrap().iter().any(|k| {
                    let rule_key = zenoh::key_expr::KeyExpr::try_from(k.as_str().unwrap()).unwrap();
                    rule_key.includes(&key)
                })
        })
    }

    #[test]
    fn zenoh_accepts_the_policy() {
        for identity in [Identity::Certificates, Identity::None] {
            let mut config = zenoh::Config::default();
            config.insert_json5("access_control", &policy("run-1", identity).to_string()).unwrap();
        }
    }

    #[test]
    fn no_remote_session_may_put_weights_or_control_or_serve_queries() {
        for (identity, subjects) in
            [(Identity::Certificates, &["actors", "observers"][..]), (Identity::None, &["remote"])]
        {
            let policy = policy("r", identity);
            assert_eq!(policy["default_permission"], "deny");
            for subject in subjects {
                let rules = rules_for(&policy, subject);
                for key in [
                    keys::weights("r"),
                    keys::control("r"),
                    keys::info("r"),
                    keys::credit("r", 0),
                    format!("{}/r/**", keys::ROOT),
                ] {
                    assert!(!allows(&rules, "ingress", "put", &key), "{subject} may put {key}");
                    assert!(!allows(&rules, "ingress", "declare_queryable", &key), "{subject} may serve {key}");
                }
                for key in [keys::transitions("r", 0), keys::all_transitions("r"), format!("{}/r/**", keys::ROOT)] {
                    assert!(!allows(&rules, "ingress", "declare_subscriber", &key), "{subject} may subscribe {key}");
                }
            }
        }
    }

    #[test]
    fn actors_may_do_what_the_actor_loop_does() {
        let certified = rules_for(&policy("r", Identity::Certificates), "actors");
        let plain = rules_for(&policy("r", Identity::None), "remote");
        for rules in [certified, plain] {
            assert!(allows(&rules, "ingress", "put", &keys::transitions("r", 3)));
            assert!(allows(&rules, "ingress", "put", &keys::stats("r", 3)));
            assert!(allows(&rules, "ingress", "put", &keys::status("r", 1000)));
            assert!(allows(&rules, "ingress", "declare_subscriber", &keys::weights("r")));
            assert!(allows(&rules, "ingress", "declare_subscriber", &keys::control("r")));
            assert!(allows(&rules, "egress", "put", &keys::weights("r")));
            assert!(allows(&rules, "ingress", "declare_subscriber", &keys::credit("r", 3)));
            assert!(allows(&rules, "egress", "put", &keys::credit("r", 3)));
            assert!(allows(&rules, "ingress", "query", &keys::info("*")));
            assert!(allows(&rules, "ingress", "query", &keys::info("r")));
            assert!(allows(&rules, "ingress", "query", &keys::weights("r")));
            assert!(allows(&rules, "egress", "reply", &keys::info("r")));
            assert!(allows(&rules, "ingress", "liveliness_token", &keys::alive_actor("r", 7)));
            assert!(allows(&rules, "ingress", "liveliness_token", &keys::alive_evaluator("r", 1000)));
            // Not another run's topics, and not the learner's token.
            assert!(!allows(&rules, "ingress", "put", &keys::transitions("other", 3)));
            assert!(!allows(&rules, "ingress", "liveliness_token", &keys::alive_learner("r")));
        }
    }

    #[test]
    fn observers_read_everything_but_transitions() {
        let rules = rules_for(&policy("r", Identity::Certificates), "observers");
        assert!(allows(&rules, "ingress", "declare_subscriber", &keys::weights("r")));
        assert!(allows(&rules, "ingress", "declare_subscriber", &keys::all_status("r")));
        assert!(allows(&rules, "egress", "put", &keys::stats("r", 0)));
        assert!(!allows(&rules, "egress", "put", &keys::transitions("r", 0)));
        assert!(!allows(&rules, "ingress", "put", &keys::stats("r", 0)));
    }
}
