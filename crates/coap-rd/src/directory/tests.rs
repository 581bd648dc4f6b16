//! The directory on literal times: registration, replacement, update, removal, expiry,
//! lookups with their criteria and pages, the bounds, and restoring from records.

use std::collections::BTreeSet;
use std::net::SocketAddr;

use super::*;

const T0: u64 = 1_800_000_000_000;

fn addr(s: &str) -> SocketAddr {
    s.parse().expect("an address")
}

fn params(query: &str) -> Params {
    Params::parse(query.split('&').filter(|s| !s.is_empty())).expect("parameters")
}

fn query(q: &str) -> Query {
    Query::parse(q.split('&').filter(|s| !s.is_empty())).expect("a query")
}

const STATION: &str = r#"</cams>;ct=40,</cams/000000000006/color>;rt="rgbd.color";obs,</coap-group>;rt="core.gp";ct=256"#;

fn directory() -> Directory {
    Directory::new(Limits::default())
}

#[test]
fn a_registration_is_found_by_endpoint_and_by_resource() {
    let mut rd = directory();
    let peer = addr("127.0.0.6:5683");
    let r = rd
        .register(
            T0,
            peer,
            params("ep=station-6&et=coapcam.station&grp=224.0.1.188:5683&lt=60"),
            STATION,
        )
        .expect("registered");
    assert!(r.created);
    let eps = rd.lookup(T0, LookupKind::Endpoints, &query(""));
    assert_eq!(
        eps.document,
        format!(
            r#"</rd/{}>;ep=station-6;base=coap://127.0.0.6;et=coapcam.station;grp=224.0.1.188:5683;rt="core.rd-ep""#,
            r.id
        )
    );
    let res = rd.lookup(T0, LookupKind::Resources, &query("rt=rgbd.color"));
    assert_eq!(
        res.document,
        r#"<coap://127.0.0.6/cams/000000000006/color>;rt="rgbd.color";obs;anchor="coap://127.0.0.6""#
    );
    // A resource link matches what its endpoint matches, and an endpoint what any of its
    // links matches.
    assert_eq!(
        rd.lookup(T0, LookupKind::Resources, &query("ep=station-6"))
            .links,
        3
    );
    assert_eq!(
        rd.lookup(T0, LookupKind::Endpoints, &query("rt=rgbd.color"))
            .links,
        1
    );
    assert_eq!(
        rd.lookup(T0, LookupKind::Endpoints, &query("rt=rgbd.depth"))
            .links,
        0
    );
    assert_eq!(
        rd.lookup(T0, LookupKind::Resources, &query("ep=station-6&rt=core.gp"))
            .links,
        1
    );
    assert_eq!(
        rd.lookup(T0, LookupKind::Endpoints, &query("grp=224.0.1.188*"))
            .links,
        1
    );
    assert_eq!(
        rd.lookup(
            T0,
            LookupKind::Endpoints,
            &query(&format!("href=/rd/{}", r.id))
        )
        .links,
        1
    );
}

#[test]
fn the_same_name_again_replaces_the_links_at_the_same_location() {
    let mut rd = directory();
    let peer = addr("[fd00::2]:5700");
    let first = rd
        .register(T0, peer, params("ep=a"), STATION)
        .expect("first");
    let again = rd
        .register(T0 + 5, peer, params("ep=a&lt=30"), "</only>")
        .expect("again");
    assert_eq!(
        again,
        Registered {
            id: first.id,
            created: false
        }
    );
    assert_eq!(rd.len(), 1);
    let res = rd.lookup(T0, LookupKind::Resources, &query(""));
    assert_eq!(
        res.document,
        r#"<coap://[fd00::2]:5700/only>;anchor="coap://[fd00::2]:5700""#
    );
    // The same name in another sector is another endpoint.
    let other = rd
        .register(T0, peer, params("ep=a&d=floor-2"), "")
        .expect("sector");
    assert!(other.created);
    assert_ne!(other.id, first.id);
    // Another address may not take a live name over.
    assert_eq!(
        rd.register(T0, addr("[fd00::3]:5700"), params("ep=a"), ""),
        Err(RdError::NotOwner)
    );
}

#[test]
fn update_renews_and_changes_the_base_and_attributes_only_from_the_owner() {
    let mut rd = directory();
    let peer = addr("127.0.0.7:40000");
    let id = rd
        .register(
            T0,
            peer,
            params("ep=b&lt=10&base=coap://127.0.0.7:5683&et=x"),
            "</s>",
        )
        .expect("registered")
        .id;
    assert_eq!(
        rd.update(T0, addr("127.0.0.8:1"), id, params("")),
        Err(RdError::NotOwner)
    );
    assert_eq!(rd.update(T0, peer, 99, params("")), Err(RdError::NotFound));
    assert!(matches!(
        rd.update(T0, peer, id, params("ep=c")),
        Err(RdError::BadRequest(_))
    ));
    // 9 s later the update gives another 10 s (the last lifetime).
    rd.update(T0 + 9_000, peer, id, params("et=y&grp=g"))
        .expect("update");
    assert_eq!(
        rd.lookup(T0 + 15_000, LookupKind::Endpoints, &query("et=y&grp=g"))
            .links,
        1
    );
    assert_eq!(
        rd.lookup(T0 + 19_000, LookupKind::Endpoints, &query(""))
            .links,
        0
    );
    rd.update(
        T0 + 10_000,
        peer,
        id,
        params("lt=100&base=coap://[fd00::9]"),
    )
    .expect("update");
    let res = rd.lookup(T0 + 50_000, LookupKind::Resources, &query(""));
    assert_eq!(
        res.document,
        r#"<coap://[fd00::9]/s>;anchor="coap://[fd00::9]""#
    );
    assert_eq!(rd.remove(addr("127.0.0.8:1"), id), Err(RdError::NotOwner));
    rd.remove(peer, id).expect("removed");
    assert!(rd.is_empty());
    assert_eq!(rd.bytes(), 0);
    assert_eq!(rd.remove(peer, id), Err(RdError::NotFound));
}

#[test]
fn a_registration_is_gone_after_its_lifetime() {
    let mut rd = directory();
    let peer = addr("127.0.0.2:5683");
    let short = rd
        .register(T0, peer, params("ep=short&lt=2"), "</x>")
        .expect("short");
    rd.register(T0, peer, params("ep=long&lt=60"), "</y>")
        .expect("long");
    assert_eq!(rd.next_expiry(), Some(T0 + 2_000));
    assert_eq!(
        rd.lookup(T0 + 1_999, LookupKind::Endpoints, &query(""))
            .links,
        2
    );
    // Not shown once the lifetime ended, even before the sweep.
    assert_eq!(
        rd.lookup(T0 + 2_000, LookupKind::Endpoints, &query(""))
            .links,
        1
    );
    assert_eq!(rd.expire(T0 + 2_000), [short.id]);
    assert_eq!(rd.len(), 1);
    assert_eq!(rd.next_expiry(), Some(T0 + 60_000));
    // Once expired, the name is free for another address.
    rd.register(T0, addr("127.0.0.3:5683"), params("ep=long2&lt=1"), "")
        .expect("x");
    assert!(
        rd.register(T0 + 1_000, addr("127.0.0.4:5683"), params("ep=long2"), "")
            .is_ok()
    );
}

#[test]
fn pages_hold_count_links_from_page_times_count() {
    let mut rd = Directory::new(Limits {
        per_peer: 100,
        ..Limits::default()
    });
    let peer = addr("127.0.0.2:5683");
    for i in 0..25 {
        rd.register(T0, peer, params(&format!("ep=n{i:02}")), "</a>,</b>")
            .expect("reg");
    }
    let page = |q: &str| {
        let found = rd.lookup(T0, LookupKind::Endpoints, &query(q));
        link_format::parse(&found.document)
            .expect("parses")
            .iter()
            .map(|l| l.attr("ep").unwrap_or_default().to_owned())
            .collect::<Vec<_>>()
    };
    assert_eq!(page("count=3"), ["n00", "n01", "n02"]);
    assert_eq!(page("page=2&count=10"), ["n20", "n21", "n22", "n23", "n24"]);
    assert_eq!(page("page=3&count=10"), Vec::<String>::new());
    assert_eq!(page("count=2&ep=n1*"), ["n10", "n11"]);
    let res = rd.lookup(T0, LookupKind::Resources, &query("page=1&count=3"));
    assert_eq!(
        res.document,
        r#"<coap://127.0.0.2/b>;anchor="coap://127.0.0.2",<coap://127.0.0.2/a>;anchor="coap://127.0.0.2",<coap://127.0.0.2/b>;anchor="coap://127.0.0.2""#
    );
    assert!(Query::parse(["page=1"]).is_err());
    assert!(Query::parse(["count=x"]).is_err());
}

#[test]
fn targets_and_anchors_resolve_against_the_base() {
    let mut rd = directory();
    let doc = r#"</sensors/temp>;rt="temperature-c",<http://www.example.com/t>;anchor="/sensors/temp";rel="describedby",<rel>"#;
    rd.register(T0, addr("[2001:db8::1]:61616"), params("ep=node1"), doc)
        .expect("registered");
    assert_eq!(
        rd.lookup(T0, LookupKind::Resources, &query("")).document,
        concat!(
            r#"<coap://[2001:db8::1]:61616/sensors/temp>;rt="temperature-c";anchor="coap://[2001:db8::1]:61616","#,
            r#"<http://www.example.com/t>;anchor="coap://[2001:db8::1]:61616/sensors/temp";rel="describedby","#,
            r#"<coap://[2001:db8::1]:61616/rel>;anchor="coap://[2001:db8::1]:61616""#
        )
    );
    assert_eq!(
        rd.lookup(
            T0,
            LookupKind::Resources,
            &query("href=http://www.example.com/*")
        )
        .links,
        1
    );
}

#[test]
fn bad_parameters_and_documents_are_refused() {
    let mut rd = directory();
    let peer = addr("127.0.0.2:5683");
    for q in [
        vec!["ep=a", "ep=b"],
        vec!["lt=0"],
        vec!["lt=4294967296"],
        vec!["lt"],
        vec!["base=coap://h/path"],
        vec!["base=nothing"],
        vec!["=x"],
    ] {
        assert!(
            matches!(Params::parse(q.clone()), Err(RdError::BadRequest(_))),
            "{q:?}"
        );
    }
    let long = "e".repeat(64);
    assert!(Params::parse([format!("ep={long}").as_str()]).is_err());
    assert!(Params::parse(["ep=a\u{7}b"]).is_err());
    assert!(Params::parse([format!("ep={}", &long[..63]).as_str()]).is_ok());
    assert_eq!(
        rd.register(T0, peer, params(""), "</a>")
            .map_err(|e| e.code()),
        Err(Code::BAD_REQUEST)
    );
    assert_eq!(
        rd.register(T0, peer, params("ep=a"), "not link format")
            .map_err(|e| e.code()),
        Err(Code::BAD_REQUEST)
    );
    assert_eq!(
        rd.register_simple(T0, peer, params("ep=a&base=coap://x"), "")
            .map_err(|e| e.code()),
        Err(Code::BAD_REQUEST)
    );
    let big = format!("<{}>", "x".repeat(40_000));
    assert_eq!(
        rd.register(T0, peer, params("ep=a"), &big)
            .map_err(|e| e.code()),
        Err(Code::REQUEST_ENTITY_TOO_LARGE)
    );
    assert!(rd.is_empty());
}

#[test]
fn one_address_is_held_to_its_count_and_bytes_and_the_directory_to_its_own() {
    let limits = Limits {
        max_registrations: 5,
        max_bytes: 1 << 20,
        per_peer: 3,
        per_peer_bytes: 8_000,
        max_document: 32 << 10,
    };
    let mut rd = Directory::new(limits);
    let a = addr("127.0.0.2:5683");
    for i in 0..3 {
        rd.register(T0, a, params(&format!("ep=a{i}")), "</x>")
            .expect("within");
    }
    let err = rd
        .register(T0, a, params("ep=a3"), "</x>")
        .expect_err("fourth");
    assert!(matches!(err, RdError::PeerLimit { held: 3, .. }), "{err:?}");
    assert_eq!(err.code(), Code::FORBIDDEN);
    // Replacing one of its own is not one more.
    rd.register(T0, a, params("ep=a2"), "</y>")
        .expect("replace");
    // Bytes: a document that would take the address past 8,000 bytes.
    let b = addr("127.0.0.3:5683");
    let links: Vec<String> = (0..40).map(|i| format!("</r{i}>;rt=\"t\"")).collect();
    let err = rd
        .register(T0, b, params("ep=b0"), &links.join(","))
        .expect_err("bytes");
    assert!(matches!(err, RdError::PeerLimit { held: 0, .. }), "{err:?}");
    rd.register(T0, b, params("ep=b0"), "</x>").expect("small");
    rd.register(T0, b, params("ep=b1"), "</x>").expect("small");
    let err = rd
        .register(T0, addr("127.0.0.4:5683"), params("ep=c"), "</x>")
        .expect_err("full");
    assert_eq!(err, RdError::Full(5));
    assert_eq!(err.code(), Code::SERVICE_UNAVAILABLE);
    let counted: usize = rd.regs.values().map(Registration::cost).sum();
    assert_eq!(rd.bytes(), counted);
}

#[test]
fn records_restore_what_was_registered_except_what_expired() {
    let mut rd = directory();
    let peer = addr("127.0.0.2:5683");
    let a = rd
        .register(T0, peer, params("ep=a&lt=100&et=coapcam.station"), STATION)
        .expect("a");
    let b = rd
        .register(T0, peer, params("ep=b&lt=5"), "</x>")
        .expect("b");
    let records: Vec<Record> = [a.id, b.id]
        .iter()
        .filter_map(|id| rd.get(*id))
        .map(|r| r.record().clone())
        .collect();
    let json = serde_json::to_string(&records).expect("serializes");
    let back: Vec<Record> = serde_json::from_str(&json).expect("parses");
    let mut restored = directory();
    assert_eq!(restored.restore(T0 + 10_000, back), 1);
    assert_eq!(
        restored.lookup(T0 + 10_000, LookupKind::Resources, &query("")),
        rd.lookup(T0 + 10_000, LookupKind::Resources, &query(""))
    );
    // New registrations get new numbers.
    let next = restored.register(T0, peer, params("ep=c"), "").expect("c");
    assert!(![a.id, b.id].contains(&next.id));
}

#[test]
fn locations_are_random_64_bit_numbers_not_a_sequence() {
    let peer = addr("127.0.0.2:5683");
    let mut rd = Directory::new(Limits {
        per_peer: 100,
        ..Limits::default()
    });
    let ids: Vec<u64> = (0..50)
        .map(|i| {
            rd.register(T0, peer, params(&format!("ep=n{i}")), "")
                .expect("registered")
                .id
        })
        .collect();
    let distinct: BTreeSet<u64> = ids.iter().copied().collect();
    assert_eq!(distinct.len(), ids.len());
    // Neither small nor one after another: knowing one location tells nothing of the
    // next.
    assert!(ids.iter().all(|id| *id > u64::from(u32::MAX)), "{ids:?}");
    assert!(ids.windows(2).all(|w| w[1].abs_diff(w[0]) > 1), "{ids:?}");
    // Another directory gives other numbers for the same registrations.
    let mut other = directory();
    let first = other
        .register(T0, peer, params("ep=n0"), "")
        .expect("registered");
    assert_ne!(first.id, ids[0]);
}

#[test]
fn an_update_never_moves_the_base_of_a_registration_made_without_one() {
    let mut rd = directory();
    let station = addr("[fd00::3]:5683");
    let id = rd
        .register(T0, station, params("ep=victim&lt=60"), "</cams>")
        .expect("registered")
        .id;
    let base = |rd: &Directory| {
        let found = rd.lookup(T0 + 1_000, LookupKind::Endpoints, &query("ep=victim"));
        link_format::parse(&found.document).expect("parses")[0]
            .attr("base")
            .map(str::to_owned)
    };
    assert_eq!(base(&rd).as_deref(), Some("coap://[fd00::3]"));
    // The issue's forged update: a base and a long lifetime, from the station's address.
    assert_eq!(
        rd.update(
            T0 + 1_000,
            station,
            id,
            params("base=coap://[fd00::66]&lt=100000")
        ),
        Err(RdError::BaseFixed)
    );
    assert_eq!(RdError::BaseFixed.code(), Code::FORBIDDEN);
    // An update from another port of the same address renews, and the base stays.
    rd.update(T0 + 1_000, addr("[fd00::3]:40000"), id, params("lt=30"))
        .expect("renewed");
    assert_eq!(base(&rd).as_deref(), Some("coap://[fd00::3]"));
    // A simple registration has no base of its own either.
    let simple = rd
        .register_simple(T0, station, params("ep=simple"), "</s>")
        .expect("simple")
        .id;
    assert_eq!(
        rd.update(T0, station, simple, params("base=coap://[fd00::66]")),
        Err(RdError::BaseFixed)
    );
}

#[test]
fn lifetimes_are_capped_at_25_hours_when_registered_updated_or_restored() {
    let mut rd = directory();
    let peer = addr("127.0.0.2:5683");
    let cap_ms = u64::from(MAX_LIFETIME_S) * 1000;
    let id = rd
        .register(T0, peer, params("ep=long&lt=4294967295"), "</x>")
        .expect("registered")
        .id;
    let record = |rd: &Directory| rd.get(id).expect("held").record().clone();
    assert_eq!(record(&rd).lt, MAX_LIFETIME_S);
    assert_eq!(record(&rd).expires_ms, T0 + cap_ms);
    assert_eq!(rd.next_expiry(), Some(T0 + cap_ms));
    rd.update(T0 + 1_000, peer, id, params("lt=100000"))
        .expect("updated");
    assert_eq!(record(&rd).lt, MAX_LIFETIME_S);
    assert_eq!(record(&rd).expires_ms, T0 + 1_000 + cap_ms);
    assert_eq!(rd.expire(T0 + 1_000 + cap_ms), [id]);
    // A record written before the cap (2^32-1 s) lives at most the cap after a restart.
    let mut old = only_record(&directory_with(peer, "ep=old&lt=60"));
    old.lt = u32::MAX;
    old.expires_ms = T0 + u64::from(u32::MAX) * 1000;
    let mut restored = directory();
    assert_eq!(restored.restore(T0, [old.clone()]), 1);
    let back = restored.get(old.id).expect("restored").record();
    assert_eq!((back.lt, back.expires_ms), (MAX_LIFETIME_S, T0 + cap_ms));
}

/// A directory holding one registration of `query` by `peer`.
fn directory_with(peer: SocketAddr, query: &str) -> Directory {
    let mut rd = directory();
    rd.register(T0, peer, params(query), "</x>")
        .expect("registered");
    rd
}

/// The record of the only registration `rd` holds.
fn only_record(rd: &Directory) -> Record {
    rd.regs.values().next().expect("one").record().clone()
}

#[test]
fn an_ipv6_slash_64_is_one_client_and_ipv4_mapped_is_ipv4() {
    let limits = Limits {
        per_peer: 3,
        ..Limits::default()
    };
    let mut rd = Directory::new(limits);
    // Four addresses of one /64, as one host may take: the fourth is over.
    for i in 1..=3 {
        rd.register(
            T0,
            addr(&format!("[fd00::1:0:0:{i}]:5683")),
            params(&format!("ep=a{i}")),
            "",
        )
        .expect("within");
    }
    let err = rd
        .register(T0, addr("[fd00::ffff:0:0:9]:5683"), params("ep=a4"), "")
        .expect_err("the same /64");
    assert!(matches!(err, RdError::PeerLimit { held: 3, .. }), "{err:?}");
    // Another /64 is another client.
    rd.register(T0, addr("[fd00:0:0:1::1]:5683"), params("ep=b"), "")
        .expect("another /64");
    // 192.0.2.1 and ::ffff:192.0.2.1 are one.
    for i in 0..3 {
        rd.register(T0, addr("192.0.2.1:5683"), params(&format!("ep=c{i}")), "")
            .expect("within");
    }
    let err = rd
        .register(T0, addr("[::ffff:192.0.2.1]:5683"), params("ep=c3"), "")
        .expect_err("the same IPv4 address");
    assert!(matches!(err, RdError::PeerLimit { held: 3, .. }), "{err:?}");
    // Removing one frees its place for the whole /64.
    let id = rd.find(None, "a2").expect("a2").record().id;
    rd.remove(addr("[fd00::1:0:0:2]:5683"), id)
        .expect("removed");
    rd.register(T0, addr("[fd00::ffff:0:0:9]:5683"), params("ep=a4"), "")
        .expect("a place again");
}

#[test]
fn an_update_after_the_lifetime_ended_does_not_bring_the_registration_back() {
    let mut rd = directory();
    let peer = addr("127.0.0.2:5683");
    let short = rd
        .register(T0, peer, params("ep=short&lt=2"), "</x>")
        .expect("short");
    // The lifetime has ended, the sweep has not run yet: a late renewal is refused.
    assert!(matches!(
        rd.update(T0 + 2_500, peer, short.id, params("")),
        Err(RdError::NotFound)
    ));
    assert_eq!(
        rd.lookup(T0 + 2_500, LookupKind::Endpoints, &query(""))
            .links,
        0
    );
    assert_eq!(rd.expire(T0 + 2_500), [short.id]);
}

/// `listing`'s document read in blocks of `size` bytes.
fn read_all(rd: &Directory, listing: &Listing, size: usize) -> Option<Vec<u8>> {
    let mut read = Vec::new();
    for start in (0..listing.len()).step_by(size) {
        read.extend(rd.read(listing, start..(start + size).min(listing.len()))?);
    }
    Some(read)
}

#[test]
fn a_listing_reads_as_the_lookups_document_until_a_registration_in_it_changes() {
    let mut rd = directory();
    let peer = addr("127.0.0.9:5683");
    let mut ids = Vec::new();
    for i in 0..5 {
        let links = format!(r#"</a{i}>;rt="x";title="café {i}",</b{i}>;rt="y",</c{i}>;rt="x""#);
        let q = format!("ep=e{i}&base=coap://127.0.0.{i}&lt=100");
        ids.push(
            rd.register(T0, peer, params(&q), &links)
                .expect("registered")
                .id,
        );
    }
    let queries = [
        "",
        "rt=x",
        "page=1&count=4",
        "page=2&count=3",
        "ep=e3",
        "title=caf*",
    ];
    for kind in [LookupKind::Endpoints, LookupKind::Resources] {
        for q in queries {
            let found = rd.lookup(T0, kind, &query(q));
            let listing = rd.listing(T0, kind, &query(q));
            assert_eq!(
                (listing.len(), listing.links()),
                (found.document.len(), found.links)
            );
            // Blocks cut through links, and through the two bytes of "é".
            for size in [1, 7, 16, 1024] {
                let read = read_all(&rd, &listing, size).expect("readable");
                assert_eq!(read, found.document.as_bytes(), "{kind:?} {q:?} in {size}");
            }
        }
    }
    let listing = rd.listing(T0, LookupKind::Resources, &query(""));
    let whole = rd.lookup(T0, LookupKind::Resources, &query("")).document;
    // Registration 2's links: from the comma before its first link to registration 3's.
    let at = |i: usize| {
        whole
            .find(&format!("<coap://127.0.0.{i}/a{i}>"))
            .expect("listed")
            - 1
    };
    let (two, three) = (at(2)..at(3), at(3)..whole.len());
    // A renewal shows the same: still readable.
    rd.update(T0 + 1_000, peer, ids[2], params("lt=100"))
        .expect("renewed");
    assert_eq!(
        read_all(&rd, &listing, 16).expect("readable"),
        whole.as_bytes()
    );
    // A new base changes what registration 2 shows: its blocks are gone, the others not.
    rd.update(T0 + 2_000, peer, ids[2], params("base=coap://127.0.0.99"))
        .expect("updated");
    assert_eq!(rd.read(&listing, two.start + 1..two.start + 2), None);
    assert_eq!(
        rd.read(&listing, 0..two.start).as_deref(),
        Some(&whole.as_bytes()[..two.start])
    );
    rd.remove(peer, ids[3]).expect("removed");
    assert_eq!(rd.read(&listing, three), None);
    // A listing holds a few words per registration, not the text.
    let big = rd.listing(T0 + 3_000, LookupKind::Resources, &query(""));
    assert!(big.held() < 1024, "{} bytes held", big.held());
}
