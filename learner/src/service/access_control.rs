//! The zenoh access-control policy of the learner's router. It is always on.
//!
//! Everything not allowed below is denied. The learner's own publications (weights, control,
//! insert credits) and queryables (run info, weights) come from its in-process session, which no ACL rule
//! sees: only the remote faces of the router are filtered. So:
//!
//! - actors may put transitions, stats and status of this run, subscribe to its weights,
//!   control and insert credits, query run info and weights, and declare their liveliness
//!   token; evaluators the same but transitions and credits;
//! - only the learner publishes weights, control and insert credits and serves the run's
//!   queryables: no remote session may put on those keys or declare a queryable, so forged
//!   weights, a forged stop, forged credit or a forged run info reach nobody;
//! - no remote session may subscribe to transitions: a subscriber that never reads would
//!   stall the actors' reliable, blocking publications (and so the learner's ingest).
//!
//! Who is who: under mutual TLS, a session whose client certificate's common name is
//! `crawler-actor-<id>` is actor `<id>` and may use that id's keys and no other's (its
//! transitions, stats, status, token and credit), likewise `crawler-evaluator-<id>`
//! ([`identity`] holds the names and the id ranges); read-only monitors carry
//! [`OBSERVER_COMMON_NAME`] and may subscribe to and query the run's weights, control, stats,
//! status and liveliness, and put nothing (`deploy/make-tls.sh` issues all three); any other
//! certificate the CA signed may do nothing. zenoh matches exact common names (no patterns),
//! so the policy lists one subject per certified id.
//! Without TLS nothing tells sessions apart, so every remote session gets the rights of any
//! actor and no more: plain TCP is for loopback and trusted networks (the learner refuses a
//! plain listener on any other address unless told `--allow-plain-remote`).
//!
//! zenoh drops denied messages silently (no error reaches the sender), which is why the
//! security tests check what actually arrives (`tests/tests/it/security.rs`).

use crawler_proto::identity::{self, Certified, OBSERVER_COMMON_NAME};
use crawler_proto::keys;
use serde_json::{Value, json};

/// How remote sessions are identified.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Identity {
    /// Mutual TLS: role and id by certificate common name ([`identity`]).
    Certificates,
    /// Plain TCP: every remote session is an actor, of any id.
    None,
}

/// A rule of the policy: `permission: allow` for `messages` on `key_exprs` in one `flow`.
fn rule(id: &str, flow: &str, messages: &[&str], key_exprs: &[&str]) -> Value {
    json!({
        "id": id,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": key_exprs,
    })
}

/// The `access_control` section of the router's zenoh config for run `run`.
///
/// Long on purpose: the policy is one JSON document (rules, subjects, policies), kept whole
/// so that it reads as zenoh's configuration reference describes it.
pub fn policy(run: &str, identity: Identity) -> Value {
    let stats = keys::all_stats(run);
    let status = keys::all_status(run);
    let weights = keys::weights(run);
    let control = keys::control(run);
    let info = keys::info(run);
    // Actors that were not told their run ask `crawler/*/info`; the ACL allows a query only
    // when a rule's key includes the query's, so discovery needs the wildcard form.
    let any_info = keys::info("*");
    let alive = format!("{}/{run}/alive/**", keys::ROOT);
    let whole_run = format!("{}/{run}/**", keys::ROOT);

    // What every actor and evaluator does that names no id: follow the learner.
    let mut rules = vec![
        rule("node-subscribes", "ingress", &["declare_subscriber"], &[&weights, &control]),
        rule("node-receives", "egress", &["put"], &[&weights, &control]),
        rule("node-queries", "ingress", &["query"], &[&any_info, &weights]),
        rule("node-gets-replies", "egress", &["reply"], &[&info, &weights]),
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
    let follows_the_learner =
        ["node-subscribes", "node-receives", "node-queries", "node-gets-replies", "learner-declarations-reach-remotes"];
    let observer_rules = json!([
        "observer-subscribes",
        "observer-queries",
        "observer-watches-liveliness",
        "observer-receives",
        "observer-sees-liveliness",
        "learner-declarations-reach-remotes",
    ]);
    let (subjects, policies) = match identity {
        Identity::Certificates => {
            let mut subjects = vec![json!({ "id": "observers", "cert_common_names": [OBSERVER_COMMON_NAME] })];
            let mut policies = vec![json!({ "id": "observers", "subjects": ["observers"], "rules": observer_rules })];
            // One subject per certified id, whose rules name that id's keys only: actor 0's
            // certificate can put, subscribe and declare tokens as actor 0 and nobody else.
            let nodes = identity::CERTIFIED_ACTOR_IDS
                .map(Certified::Actor)
                .chain(identity::CERTIFIED_EVALUATOR_IDS.map(Certified::Evaluator));
            for node in nodes {
                let name = node.common_name();
                let own_rules = own_keys(run, node);
                let mut rule_ids: Vec<Value> = follows_the_learner.iter().map(|id| json!(id)).collect();
                rule_ids.extend(own_rules.iter().map(|r| r["id"].clone()));
                rules.extend(own_rules);
                subjects.push(json!({ "id": name, "cert_common_names": [name] }));
                policies.push(json!({ "id": name, "subjects": [name], "rules": rule_ids }));
            }
            (json!(subjects), json!(policies))
        }
        // A subject with no property matches every remote session; ids are told apart only by
        // the learner, which takes each in its one canonical spelling.
        Identity::None => {
            let any_node = node_rules(
                "any-node",
                &[&keys::all_transitions(run), &stats, &status],
                &[&keys::all_alive_actors(run), &keys::all_alive_evaluators(run)],
                Some(&keys::all_credits(run)),
            );
            let mut rule_ids: Vec<Value> = follows_the_learner.iter().map(|id| json!(id)).collect();
            rule_ids.extend(any_node.iter().map(|r| r["id"].clone()));
            rules.extend(any_node);
            (
                json!([{ "id": "remote" }]),
                json!([{ "id": "remote-sessions-are-actors", "subjects": ["remote"], "rules": rule_ids }]),
            )
        }
    };
    json!({
        "enabled": true,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    })
}

/// The rules that let certified `node` use its own id's keys: an actor puts its transitions,
/// stats and status, declares its token and takes its insert credit; an evaluator puts stats
/// and status and declares its token. Observers have no id.
fn own_keys(run: &str, node: Certified) -> Vec<Value> {
    let name = node.common_name();
    match node {
        Certified::Actor(id) => node_rules(
            &name,
            &[&keys::transitions(run, id), &keys::stats(run, id), &keys::status(run, id)],
            &[&keys::alive_actor(run, id)],
            Some(&keys::credit(run, id)),
        ),
        Certified::Evaluator(id) => node_rules(
            &name,
            &[&keys::stats(run, id), &keys::status(run, id)],
            &[&keys::alive_evaluator(run, id)],
            None,
        ),
        Certified::Observer => Vec::new(),
    }
}

/// The rules, named `<name>-…`, that let a node put on `publishes`, declare liveliness tokens
/// on `tokens` and, given `credit`, subscribe to and receive its insert credit there: one
/// certified id's keys, or (over plain TCP) every id's.
fn node_rules(name: &str, publishes: &[&str], tokens: &[&str], credit: Option<&str>) -> Vec<Value> {
    let mut rules = vec![
        rule(&format!("{name}-publishes"), "ingress", &["put"], publishes),
        rule(&format!("{name}-liveliness"), "ingress", &["liveliness_token"], tokens),
    ];
    if let Some(credit) = credit {
        rules.push(rule(&format!("{name}-subscribes-credit"), "ingress", &["declare_subscriber"], &[credit]));
        rules.push(rule(&format!("{name}-receives-credit"), "egress", &["put"], &[credit]));
    }
    rules
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

    /// Every subject of a policy, by id.
    fn subjects(policy: &Value) -> Vec<String> {
        policy["subjects"].as_array().unwrap().iter().map(|s| s["id"].as_str().unwrap().to_string()).collect()
    }

    #[test]
    fn no_remote_session_may_put_weights_or_control_or_serve_queries() {
        for identity in [Identity::Certificates, Identity::None] {
            let policy = policy("r", identity);
            assert_eq!(policy["default_permission"], "deny");
            for subject in subjects(&policy) {
                let rules = rules_for(&policy, &subject);
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

    /// What the actor loop of actor `id` does, and evaluator `id`'s.
    fn assert_may_act_as(rules: &[Value], id: u32, evaluator: bool) {
        assert!(allows(rules, "ingress", "put", &keys::stats("r", id)));
        assert!(allows(rules, "ingress", "put", &keys::status("r", id)));
        assert!(allows(rules, "ingress", "declare_subscriber", &keys::weights("r")));
        assert!(allows(rules, "ingress", "declare_subscriber", &keys::control("r")));
        assert!(allows(rules, "egress", "put", &keys::weights("r")));
        assert!(allows(rules, "ingress", "query", &keys::info("*")));
        assert!(allows(rules, "ingress", "query", &keys::info("r")));
        assert!(allows(rules, "ingress", "query", &keys::weights("r")));
        assert!(allows(rules, "egress", "reply", &keys::info("r")));
        if evaluator {
            assert!(allows(rules, "ingress", "liveliness_token", &keys::alive_evaluator("r", id)));
        } else {
            assert!(allows(rules, "ingress", "put", &keys::transitions("r", id)));
            assert!(allows(rules, "ingress", "declare_subscriber", &keys::credit("r", id)));
            assert!(allows(rules, "egress", "put", &keys::credit("r", id)));
            assert!(allows(rules, "ingress", "liveliness_token", &keys::alive_actor("r", id)));
        }
        // Not another run's topics, and not the learner's token.
        assert!(!allows(rules, "ingress", "put", &keys::transitions("other", id)));
        assert!(!allows(rules, "ingress", "liveliness_token", &keys::alive_learner("r")));
    }

    #[test]
    fn any_plain_session_may_act_as_any_actor() {
        let plain = rules_for(&policy("r", Identity::None), "remote");
        for (id, evaluator) in [(0, false), (3, false), (7_000, false), (1000, true)] {
            assert_may_act_as(&plain, id, evaluator);
        }
    }

    #[test]
    fn a_certificate_acts_as_its_own_id_and_no_other() {
        let policy = policy("r", Identity::Certificates);
        let actor = |id| rules_for(&policy, &Certified::Actor(id).common_name());
        let evaluator = |id| rules_for(&policy, &Certified::Evaluator(id).common_name());
        for id in [0, 1, 999] {
            assert_may_act_as(&actor(id), id, false);
        }
        for id in [1000, 1999] {
            assert_may_act_as(&evaluator(id), id, true);
        }
        // Actor 0's certificate, as actor 1 (or as the evaluator id space): nothing.
        let zero = actor(0);
        for other in [1, 1000] {
            for key in [keys::transitions("r", other), keys::stats("r", other), keys::status("r", other)] {
                assert!(!allows(&zero, "ingress", "put", &key), "actor 0 may put {key}");
            }
            assert!(!allows(&zero, "ingress", "liveliness_token", &keys::alive_actor("r", other)));
            assert!(!allows(&zero, "ingress", "liveliness_token", &keys::alive_evaluator("r", other)));
            assert!(!allows(&zero, "ingress", "declare_subscriber", &keys::credit("r", other)));
            assert!(!allows(&zero, "egress", "put", &keys::credit("r", other)));
        }
        // Its own id in another spelling, and wildcards over ids, are not its id.
        for key in ["crawler/r/transitions/00", "crawler/r/transitions/*", "crawler/r/status/**"] {
            assert!(!allows(&zero, "ingress", "put", key), "actor 0 may put {key}");
        }
        assert!(!allows(&zero, "ingress", "liveliness_token", "crawler/r/alive/actor/*"));
        assert!(!allows(&zero, "ingress", "declare_subscriber", &keys::all_credits("r")));
        // An evaluator takes no transitions and no credit, even its own id's.
        let evaluator = evaluator(1000);
        assert!(!allows(&evaluator, "ingress", "put", &keys::transitions("r", 1000)));
        assert!(!allows(&evaluator, "ingress", "declare_subscriber", &keys::credit("r", 1000)));
        // Every certified id has its own subject, and nothing else but the observers does.
        let expected = identity::CERTIFIED_ACTOR_IDS.len() + identity::CERTIFIED_EVALUATOR_IDS.len() + 1;
        assert_eq!(subjects(&policy).len(), expected);
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
