//! Which subject of the end-to-end suite uses which DDS domain.
//!
//! The suite is one test binary whose tests all run side by side, and two tests in one domain
//! see each other's samples (the same topics, the same types): a reader that must get each
//! sample once would get some twice. So each module keeps to domains no other module uses;
//! tests within a module share them knowingly (they ran side by side as a binary of their
//! own before). A Cyclone peer and a test client's participant claim their domain here; a
//! domain claimed by two modules fails the second claimant's test at once, whichever order
//! the tests ran in, so a clash is a red test, not a flaky one.

use std::collections::BTreeMap;
use std::sync::Mutex;

/// The domain id a client names for "the agent's default" (the agent maps it to
/// `XRCE_DOMAIN_ID_OVERRIDE`, `ROS_DOMAIN_ID` or 0); the peer in the real domain claims that.
const AGENT_DEFAULT: u32 = 255;

/// Records that the running test's module uses `domain`; panics if another module does.
///
/// The module is read from the thread libtest runs the test on (named `module::test`, or
/// `module::inner::test` for a test in a nested module, which counts as its top module's).
/// Threads a test starts itself are unnamed and claim nothing: the test's own claims cover
/// them. Outside a suite of modules (a name without `::`) nothing is checked.
pub fn claim(domain: u32) {
    if domain == AGENT_DEFAULT {
        return;
    }
    let thread = std::thread::current();
    let Some((module, _)) = thread.name().and_then(|name| name.split_once("::")) else {
        return;
    };
    static CLAIMS: Mutex<BTreeMap<u32, String>> = Mutex::new(BTreeMap::new());
    let mut claims = CLAIMS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let holder = claims
        .entry(domain)
        .or_insert_with(|| module.to_string())
        .clone();
    drop(claims);
    assert!(
        holder == module,
        "DDS domain {domain} is used by the tests of both `{holder}` and `{module}`, which run \
         side by side and would read each other's samples: give one of them a domain of its own"
    );
}

/// The domain a `dds_peer.py` command line names (`--domain N`; 0, the script's default,
/// when it names none).
pub(crate) fn of_peer_arguments(args: &[&str]) -> u32 {
    args.windows(2)
        .find(|w| w[0] == "--domain")
        .and_then(|w| w[1].parse().ok())
        .unwrap_or(0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_peer_without_a_domain_is_in_domain_0() {
        assert_eq!(of_peer_arguments(&["read", "--count", "3"]), 0);
        assert_eq!(of_peer_arguments(&["read", "--domain", "24"]), 24);
    }

    #[test]
    fn a_second_module_in_a_domain_fails_and_the_first_may_claim_it_again() {
        let run = |name: &str, domain: u32| {
            std::thread::Builder::new()
                .name(name.into())
                .spawn(move || claim(domain))
                .expect("thread")
                .join()
                .is_ok()
        };
        assert!(run("first::a", 231));
        assert!(run("first::b", 231));
        assert!(!run("second::c", 231));
        assert!(run("second::c", 230));
        // A nested module is its top module's.
        assert!(run("first::inner::d", 231));
    }
}
