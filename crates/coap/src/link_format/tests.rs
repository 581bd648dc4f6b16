//! The link format's parser, writer and filter against RFC 6690's examples and edge cases.

use proptest::prelude::*;

use super::*;

fn filter(query: &str) -> Filter {
    Filter::parse(query).unwrap_or_else(|e| panic!("{query:?}: {e}"))
}

fn targets<'a>(links: &'a [Link], query: &str) -> Vec<&'a str> {
    let f = filter(query);
    links
        .iter()
        .filter(|l| f.matches(l))
        .map(|l| l.target.as_str())
        .collect()
}

/// RFC 6690 §5, the sensor directory with anchors and relations.
const RFC6690_SENSORS: &str = "</sensors>;ct=40;title=\"Sensor Index\",\n\
    </sensors/temp>;rt=\"temperature-c\";if=\"sensor\",\n\
    </sensors/light>;rt=\"light-lux\";if=\"sensor\",\n\
    <http://www.example.com/sensors/t123>;anchor=\"/sensors/temp\";rel=\"describedby\",\n\
    </t>;anchor=\"/sensors/temp\";rel=\"alternate\"";

#[test]
fn rfc6690_section5_sensor_directory() {
    let links = parse(RFC6690_SENSORS).unwrap();
    let expected = vec![
        Link::new("/sensors")
            .with_ct(ContentFormat::LINK_FORMAT)
            .with_title("Sensor Index"),
        Link::new("/sensors/temp")
            .with_rt("temperature-c")
            .with_if("sensor"),
        Link::new("/sensors/light")
            .with_rt("light-lux")
            .with_if("sensor"),
        Link::new("http://www.example.com/sensors/t123")
            .with_attr("anchor", "/sensors/temp")
            .with_attr("rel", "describedby"),
        Link::new("/t")
            .with_attr("anchor", "/sensors/temp")
            .with_attr("rel", "alternate"),
    ];
    assert_eq!(links, expected);
    assert_eq!(write_links(&links), RFC6690_SENSORS.replace('\n', ""));
    assert_eq!(links[0].title(), Some("Sensor Index"));
    assert_eq!(
        links[0].ct().collect::<Vec<_>>(),
        [ContentFormat::LINK_FORMAT]
    );
}

#[test]
fn rfc6690_section5_simple_and_firmware_examples() {
    let links = parse("</sensors/temp>;if=\"sensor\",\n</sensors/light>;if=\"sensor\"").unwrap();
    assert_eq!(links.len(), 2);
    assert_eq!(links[1].interfaces().collect::<Vec<_>>(), ["sensor"]);

    let links = parse("</firmware/v2.1>;rt=\"firmware\";sz=262144").unwrap();
    assert_eq!(
        links,
        [Link::new("/firmware/v2.1")
            .with_rt("firmware")
            .with_sz(262_144)]
    );
    assert_eq!(links[0].sz(), Some(262_144));
}

#[test]
fn quoted_strings_hold_commas_semicolons_and_escapes() {
    let links =
        parse(r#"</a>;title="one, two; three";x="say \"hi\" \\ bye",</b>;title="<c>""#).unwrap();
    assert_eq!(links.len(), 2);
    assert_eq!(links[0].title(), Some("one, two; three"));
    assert_eq!(links[0].attr("x"), Some(r#"say "hi" \ bye"#));
    assert_eq!(links[1].title(), Some("<c>"));
    assert_eq!(parse(&write_links(&links)).unwrap(), links);
}

#[test]
fn valueless_and_repeated_attributes_keep_order() {
    let links = parse("</obs>;obs;rt=a;rt=\"b c\";ct=\"40 50\";ct=60").unwrap();
    let link = &links[0];
    assert_eq!(
        link.attrs,
        [
            ("obs".to_owned(), None),
            ("rt".to_owned(), Some("a".to_owned())),
            ("rt".to_owned(), Some("b c".to_owned())),
            ("ct".to_owned(), Some("40 50".to_owned())),
            ("ct".to_owned(), Some("60".to_owned())),
        ]
    );
    assert!(link.obs());
    assert_eq!(link.rt().collect::<Vec<_>>(), ["a", "b", "c"]);
    assert_eq!(
        link.ct().collect::<Vec<_>>(),
        [
            ContentFormat::LINK_FORMAT,
            ContentFormat::JSON,
            ContentFormat::CBOR
        ]
    );
    assert_eq!(
        write_links(&links),
        "</obs>;obs;rt=\"a\";rt=\"b c\";ct=\"40 50\";ct=60"
    );
}

#[test]
fn whitespace_between_links_and_params() {
    let links = parse(" \r\n</a> ;\tct=0 ,\n\n </b>;obs \n").unwrap();
    assert_eq!(
        links,
        [
            Link::new("/a").with_ct(ContentFormat::TEXT_PLAIN),
            Link::new("/b").with_obs()
        ]
    );
}

#[test]
fn empty_document_is_empty_list() {
    assert_eq!(parse(""), Ok(vec![]));
    assert_eq!(parse(" \n"), Ok(vec![]));
    assert_eq!(write_links(&[]), "");
}

#[test]
fn parse_errors_name_kind_and_offset() {
    let cases: &[(&str, ParseErrorKind, usize)] = &[
        ("/a", ParseErrorKind::ExpectedLink, 0),
        ("</a", ParseErrorKind::UnterminatedTarget, 0),
        ("</a>;", ParseErrorKind::ExpectedAttrName, 5),
        ("</a>;=1", ParseErrorKind::ExpectedAttrName, 5),
        ("</a>;ct=", ParseErrorKind::ExpectedValue, 8),
        ("</a>;ct=,", ParseErrorKind::ExpectedValue, 8),
        (
            "</a>;title=\"x",
            ParseErrorKind::UnterminatedQuotedString,
            11,
        ),
        (
            "</a>;title=\"x\\",
            ParseErrorKind::UnterminatedQuotedString,
            11,
        ),
        ("</a>;ct=4 0", ParseErrorKind::ExpectedSeparator, 10),
        ("</a></b>", ParseErrorKind::ExpectedSeparator, 4),
        ("</a>,", ParseErrorKind::ExpectedLink, 5),
        ("</a>,,</b>", ParseErrorKind::ExpectedLink, 5),
    ];
    for &(input, kind, offset) in cases {
        assert_eq!(parse(input), Err(ParseError { kind, offset }), "{input:?}");
    }
    let message = parse("</a>;ct=").map_err(|e| e.to_string());
    assert_eq!(
        message,
        Err(
            "invalid link-format at byte 8: expected a token or a quoted string after '='"
                .to_owned()
        )
    );
}

#[test]
fn writer_quotes_only_where_needed() {
    let link = Link::new("/x")
        .with_ct(ContentFormat::JSON)
        .with_sz(10)
        .with_attr("foo", "bar")
        .with_attr("empty", "")
        .with_attr("sp", "a b")
        .with_attr("q", "a\"b\\c")
        .with_attr("title*", "UTF-8'de'n%c3%a4chstes")
        .with_title("T");
    assert_eq!(
        link.to_string(),
        r#"</x>;ct=50;sz=10;foo=bar;empty="";sp="a b";q="a\"b\\c";title*=UTF-8'de'n%c3%a4chstes;title="T""#
    );
    assert_eq!(parse(&link.to_string()).unwrap(), [link]);
}

#[test]
fn writer_escapes_gt_in_target() {
    assert_eq!(Link::new("/a>b>").to_string(), "</a%3Eb%3E>");
}

fn catalogue() -> Vec<Link> {
    vec![
        Link::new("/cams").with_ct(ContentFormat::LINK_FORMAT),
        Link::new("/cams/840412060746/color")
            .with_rt("coapcam.color core.s")
            .with_if("core.s")
            .with_attr("ct", "42 23 22")
            .with_obs(),
        Link::new("/cams/840412060746/pointcloud")
            .with_rt("coapcam.pointcloud")
            .with_attr("ct", "42 60 65100"),
        Link::new("/coap-group")
            .with_rt("core.gp")
            .with_ct(ContentFormat::COAP_GROUP_JSON),
    ]
}

#[test]
fn filter_by_href_exact_and_prefix() {
    let links = catalogue();
    assert_eq!(targets(&links, "href=/cams"), ["/cams"]);
    assert_eq!(
        targets(&links, "href=/cams*"),
        [
            "/cams",
            "/cams/840412060746/color",
            "/cams/840412060746/pointcloud"
        ]
    );
    assert_eq!(
        targets(&links, "href=/cams/840412060746/p*"),
        ["/cams/840412060746/pointcloud"]
    );
}

#[test]
fn filter_by_rt_list_membership() {
    let links = catalogue();
    assert_eq!(targets(&links, "rt=core.s"), ["/cams/840412060746/color"]);
    assert_eq!(
        targets(&links, "rt=coapcam.color"),
        ["/cams/840412060746/color"]
    );
    assert_eq!(
        targets(&links, "rt=coapcam.*"),
        ["/cams/840412060746/color", "/cams/840412060746/pointcloud"]
    );
    assert_eq!(targets(&links, "rt=core.gp"), ["/coap-group"]);
    assert_eq!(targets(&links, "if=core.s"), ["/cams/840412060746/color"]);
}

#[test]
fn filter_by_ct() {
    let links = catalogue();
    assert_eq!(targets(&links, "ct=40"), ["/cams"]);
    assert_eq!(
        targets(&links, "ct=42"),
        ["/cams/840412060746/color", "/cams/840412060746/pointcloud"]
    );
    assert_eq!(
        targets(&links, "ct=65100"),
        ["/cams/840412060746/pointcloud"]
    );
    assert_eq!(targets(&links, "ct=256"), ["/coap-group"]);
}

#[test]
fn filter_star_presence_and_valueless() {
    let links = catalogue();
    assert_eq!(targets(&links, "obs"), ["/cams/840412060746/color"]);
    assert_eq!(targets(&links, "obs=*"), ["/cams/840412060746/color"]);
    assert_eq!(targets(&links, "href=*").len(), 4);
    assert_eq!(targets(&links, "rt=*").len(), 3);
    assert_eq!(targets(&links, "").len(), 4);
    assert_eq!(targets(&links, "?").len(), 4);
}

#[test]
fn filter_no_match() {
    let links = catalogue();
    assert!(targets(&links, "rt=nothing").is_empty());
    assert!(targets(&links, "href=/nope*").is_empty());
    assert!(targets(&links, "title=x").is_empty());
    assert!(targets(&links, "rt=coapcam").is_empty());
    assert!(targets(&links, "ct=4").is_empty());
}

#[test]
fn filter_terms_combine_with_and() {
    let links = catalogue();
    assert_eq!(
        targets(&links, "href=/cams*&ct=60"),
        ["/cams/840412060746/pointcloud"]
    );
    assert!(targets(&links, "href=/coap-group&ct=60").is_empty());
}

#[test]
fn filter_percent_decoding() {
    let links = vec![Link::new("/a b").with_title("x*y"), Link::new("/a c")];
    assert_eq!(targets(&links, "href=/a%20b"), ["/a b"]);
    assert_eq!(targets(&links, "href=/a%20*"), ["/a b", "/a c"]);
    assert_eq!(targets(&links, "title=x%2Ay"), ["/a b"]);
    assert!(targets(&links, "title=x%2A").is_empty());
    assert_eq!(targets(&links, "%74itle=x*"), ["/a b"]);
}

#[test]
fn filter_errors() {
    assert_eq!(
        Filter::parse("rt=%4"),
        Err(FilterError::BadPercentEncoding { offset: 3 })
    );
    assert_eq!(
        Filter::parse("a&rt=%zz"),
        Err(FilterError::BadPercentEncoding { offset: 5 })
    );
    assert_eq!(
        Filter::parse("rt=%ff"),
        Err(FilterError::NotUtf8 { offset: 3 })
    );
    assert_eq!(
        Filter::parse("a&=x"),
        Err(FilterError::EmptyName { offset: 2 })
    );
    assert_eq!(
        Filter::parse("?=x"),
        Err(FilterError::EmptyName { offset: 1 })
    );
}

fn arb_link() -> impl Strategy<Value = Link> {
    let name = "[A-Za-z0-9!#$&+.^_`|~*-]{1,8}";
    let value = proptest::option::of(any::<String>());
    ("[^>]{0,24}", proptest::collection::vec((name, value), 0..6))
        .prop_map(|(target, attrs)| Link { target, attrs })
}

proptest! {
    #[test]
    fn parse_inverts_write(links in proptest::collection::vec(arb_link(), 0..6)) {
        prop_assert_eq!(parse(&write_links(&links)), Ok(links));
    }

    #[test]
    fn parse_never_panics(input in any::<String>()) {
        let _ = parse(&input);
    }

    #[test]
    fn parse_never_panics_on_link_like_input(input in r#"[<>;,="\\ a*\n]{0,40}"#) {
        let _ = parse(&input);
    }

    #[test]
    fn filter_never_panics(query in any::<String>(), link in arb_link()) {
        if let Ok(f) = Filter::parse(&query) {
            let _ = f.matches(&link);
        }
    }
}
