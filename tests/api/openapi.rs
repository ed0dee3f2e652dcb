//! `openapi.yaml` against the served app: the same operations, and every response these tests
//! receive (status, media type, body) is one the document describes.

use std::collections::BTreeSet;
use std::sync::OnceLock;

use serde_json::Value;

pub struct Spec {
    doc: Value,
}

pub fn spec() -> &'static Spec {
    static SPEC: OnceLock<Spec> = OnceLock::new();
    SPEC.get_or_init(|| Spec { doc: serde_norway::from_str(facegate_http::OPENAPI_YAML).expect("openapi.yaml parses as YAML") })
}

const METHODS: [&str; 5] = ["get", "post", "put", "patch", "delete"];

impl Spec {
    /// (METHOD, path) of every operation in the document.
    pub fn operations(&self) -> BTreeSet<(String, String)> {
        let paths = self.doc["paths"].as_object().expect("paths");
        paths
            .iter()
            .flat_map(|(path, item)| METHODS.iter().filter(move |m| item.get(**m).is_some()).map(move |m| (m.to_uppercase(), path.clone())))
            .collect()
    }

    /// The path template of the document matching a concrete path (`/subjects/x` → `/subjects/{id}`).
    pub fn template_for(&self, path: &str) -> Option<String> {
        let segments: Vec<&str> = path.split('/').collect();
        self.doc["paths"]
            .as_object()?
            .keys()
            .find(|template| {
                let t: Vec<&str> = template.split('/').collect();
                t.len() == segments.len()
                    && t.iter().zip(&segments).all(|(a, b)| (a.starts_with('{') && a.ends_with('}') && !b.is_empty()) || a == b)
            })
            .cloned()
    }

    fn resolve<'a>(&'a self, mut v: &'a Value) -> &'a Value {
        while let Some(r) = v.get("$ref").and_then(Value::as_str) {
            let pointer = r.strip_prefix('#').expect("local $ref");
            v = self.doc.pointer(pointer).unwrap_or_else(|| panic!("dangling $ref {r}"));
        }
        v
    }

    /// Check one response against the document; panics with the reason when it does not fit.
    pub fn check_response(&self, method: &str, path: &str, status: u16, content_type: Option<&str>, body: &[u8]) {
        let template = self.template_for(path).unwrap_or_else(|| panic!("{path} is not in openapi.yaml"));
        let operation = &self.doc["paths"][&template][method.to_lowercase()];
        assert!(operation.is_object(), "{method} {template} is not in openapi.yaml");
        let response = operation["responses"]
            .get(status.to_string())
            .map(|r| self.resolve(r))
            .unwrap_or_else(|| panic!("openapi.yaml lists no {status} response for {method} {template}"));
        let Some(content) = response.get("content").and_then(Value::as_object) else {
            assert!(body.is_empty(), "{method} {template} {status}: the document describes no body, got {} bytes", body.len());
            return;
        };
        let essence = content_type.unwrap_or("").split(';').next().unwrap_or("").trim();
        let media = content.get(essence).unwrap_or_else(|| {
            panic!("{method} {template} {status}: media type {essence:?} is not one of {:?}", content.keys().collect::<Vec<_>>())
        });
        let schema = &media["schema"];
        if schema["format"] == "binary" {
            // glTF, PNG: the tests decode these bodies themselves.
            assert!(!body.is_empty(), "{method} {template} {status}: an empty {essence} body");
            return;
        }
        let value: Value = if essence.ends_with("json") {
            serde_json::from_slice(body).unwrap_or_else(|e| panic!("{method} {template} {status}: body is not JSON: {e}"))
        } else {
            Value::String(String::from_utf8(body.to_vec()).expect("text body"))
        };
        if let Err(e) = self.validate(schema, &value, "$") {
            panic!("{method} {template} {status}: the body does not fit openapi.yaml: {e}\nbody: {value}");
        }
        if essence == "application/problem+json" {
            assert_eq!(value["status"], status, "problem status field");
        }
    }

    /// A small JSON Schema validator for the keywords the document uses.
    pub fn validate(&self, schema: &Value, value: &Value, at: &str) -> Result<(), String> {
        let schema = self.resolve(schema);
        if let Some(types) = schema.get("type") {
            let allowed: Vec<&str> = match types {
                Value::String(t) => vec![t.as_str()],
                Value::Array(ts) => ts.iter().filter_map(Value::as_str).collect(),
                _ => return Err(format!("{at}: bad type keyword")),
            };
            let fits = |t: &str| match t {
                "object" => value.is_object(),
                "array" => value.is_array(),
                "string" => value.is_string(),
                "number" => value.is_number(),
                "integer" => value.is_i64() || value.is_u64(),
                "boolean" => value.is_boolean(),
                "null" => value.is_null(),
                _ => false,
            };
            if !allowed.iter().any(|t| fits(t)) {
                return Err(format!("{at}: {value} is not of type {allowed:?}"));
            }
            if value.is_null() {
                return Ok(());
            }
        }
        if let Some(options) = schema.get("enum").and_then(Value::as_array) {
            if !options.contains(value) {
                return Err(format!("{at}: {value} is not one of {options:?}"));
            }
        }
        if let (Some(min), Some(n)) = (schema.get("minimum").and_then(Value::as_f64), value.as_f64()) {
            if n < min {
                return Err(format!("{at}: {n} < minimum {min}"));
            }
        }
        if let Some(s) = value.as_str() {
            let len = s.chars().count() as u64;
            if schema.get("minLength").and_then(Value::as_u64).is_some_and(|m| len < m)
                || schema.get("maxLength").and_then(Value::as_u64).is_some_and(|m| len > m)
            {
                return Err(format!("{at}: length {len} out of range"));
            }
        }
        if let Some(object) = value.as_object() {
            for required in schema.get("required").and_then(Value::as_array).into_iter().flatten() {
                let name = required.as_str().unwrap();
                if !object.contains_key(name) {
                    return Err(format!("{at}: required property {name} is missing"));
                }
            }
            let properties = schema.get("properties").and_then(Value::as_object);
            for (name, v) in object {
                match properties.and_then(|p| p.get(name)) {
                    Some(s) => self.validate(s, v, &format!("{at}.{name}"))?,
                    None if schema.get("additionalProperties") == Some(&Value::Bool(false)) => {
                        return Err(format!("{at}: property {name} is not in the document"));
                    }
                    None => {}
                }
            }
        }
        if let Some(items) = value.as_array() {
            let n = items.len() as u64;
            if schema.get("minItems").and_then(Value::as_u64).is_some_and(|m| n < m)
                || schema.get("maxItems").and_then(Value::as_u64).is_some_and(|m| n > m)
            {
                return Err(format!("{at}: {n} items out of range"));
            }
            if let Some(item_schema) = schema.get("items") {
                for (i, item) in items.iter().enumerate() {
                    self.validate(item_schema, item, &format!("{at}[{i}]"))?;
                }
            }
        }
        Ok(())
    }
}

#[test]
fn the_document_lists_exactly_the_served_operations() {
    let served: BTreeSet<(String, String)> =
        facegate_http::operations().iter().map(|o| (o.method.to_string(), o.path.to_string())).collect();
    assert_eq!(spec().operations(), served);
}

#[test]
fn the_document_lists_every_problem_type() {
    let documented: BTreeSet<String> = spec().doc["components"]["schemas"]["Problem"]["properties"]["type"]["enum"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap().to_string())
        .collect();
    let served: BTreeSet<String> = facegate_http::ProblemKind::ALL.iter().map(|k| k.type_uri()).collect();
    assert_eq!(documented, served);
}

#[test]
fn every_ref_resolves_and_the_validator_rejects_misfits() {
    fn refs(v: &Value, out: &mut Vec<String>) {
        match v {
            Value::Object(m) => {
                if let Some(Value::String(r)) = m.get("$ref") {
                    out.push(r.clone());
                }
                m.values().for_each(|x| refs(x, out));
            }
            Value::Array(a) => a.iter().for_each(|x| refs(x, out)),
            _ => {}
        }
    }
    let mut all = Vec::new();
    refs(&spec().doc, &mut all);
    assert!(all.len() > 20);
    for r in all {
        assert!(spec().doc.pointer(&r[1..]).is_some(), "dangling {r}");
    }
    let problem = serde_json::json!({"$ref": "#/components/schemas/Problem"});
    let good = serde_json::json!({"type": "https://facegate.dev/problems/no-face", "title": "t", "status": 422, "detail": "d"});
    assert!(spec().validate(&problem, &good, "$").is_ok());
    let mut extra = good.clone();
    extra["surprise"] = 1.into();
    assert!(spec().validate(&problem, &extra, "$").is_err());
    let mut missing = good.clone();
    missing.as_object_mut().unwrap().remove("detail");
    assert!(spec().validate(&problem, &missing, "$").is_err());
    let mut wrong_type = good;
    wrong_type["type"] = "https://facegate.dev/problems/made-up".into();
    assert!(spec().validate(&problem, &wrong_type, "$").is_err());
}

/// Photo parts of multipart bodies carry both the OpenAPI 3.1 `contentMediaType` and `format:
/// binary`, which the common client generators read as a file (without it they send text).
#[test]
fn multipart_photo_parts_are_binary_for_generators() {
    let mut parts = 0;
    for (path, item) in spec().doc["paths"].as_object().unwrap() {
        for method in METHODS {
            let Some(properties) = item
                .get(method)
                .and_then(|op| op.pointer("/requestBody/content/multipart~1form-data/schema/properties"))
                .and_then(Value::as_object)
            else {
                continue;
            };
            for (name, property) in properties {
                let part = if property["type"] == "array" { &property["items"] } else { property };
                if part.get("$ref").is_some() {
                    continue;
                }
                assert_eq!(part["type"], "string", "{method} {path} part {name}");
                assert_eq!(part["format"], "binary", "{method} {path} part {name}: format binary");
                assert!(part["contentMediaType"].is_string(), "{method} {path} part {name}: contentMediaType");
                parts += 1;
            }
        }
    }
    assert_eq!(parts, 7, "the image parts of /enroll, /verify, /identify, /analyze, /avatar and /frontalize, and /verify's frame parts");
}
