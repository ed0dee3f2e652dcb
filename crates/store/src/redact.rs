//! A database URL as it may be printed: its password replaced with `***`, in the user information
//! (`postgres://user:***@host/db`) and in a `password` query parameter (`?password=***`), so that
//! no error, log line or problem shows it.

/// `url` with its password, if it holds one, replaced with `***`. The user information ends at
/// the last `@` (a password may hold unencoded `@`, `/` or `?`: more is hidden rather than less);
/// text that is not a URL of the form `scheme://…` is returned as it is, less any `password=`.
pub fn redact_url(url: &str) -> String {
    let mut redacted = match url.split_once("://") {
        Some((scheme, rest)) if !rest.starts_with('/') => match rest.rsplit_once('@') {
            Some((userinfo, after)) => match userinfo.split_once(':') {
                Some((user, _password)) => format!("{scheme}://{user}:***@{after}"),
                None => url.to_string(),
            },
            None => url.to_string(),
        },
        _ => url.to_string(),
    };
    if let Some(start) = redacted.find('?') {
        let query: Vec<String> = redacted[start + 1..]
            .split('&')
            .map(|parameter| match parameter.split_once('=') {
                Some((name, _)) if name.eq_ignore_ascii_case("password") => format!("{name}=***"),
                _ => parameter.to_string(),
            })
            .collect();
        redacted = format!("{}?{}", &redacted[..start], query.join("&"));
    }
    redacted
}

#[cfg(test)]
mod tests {
    use super::redact_url;

    #[test]
    fn passwords_are_replaced_everywhere_a_url_holds_one() {
        assert_eq!(redact_url("postgres://u:s3cretpw@127.0.0.1:1/db"), "postgres://u:***@127.0.0.1:1/db");
        assert_eq!(redact_url("postgresql://u:p%40ss@host/db?sslmode=require"), "postgresql://u:***@host/db?sslmode=require");
        // An @ in an unencoded password: the host is after the last one.
        assert_eq!(redact_url("postgres://u:a@b@host/db"), "postgres://u:***@host/db");
        assert_eq!(redact_url("postgres://u:a/b?c@host/db"), "postgres://u:***@host/db");
        assert_eq!(redact_url("postgres://host/db?user=u&password=s3cretpw"), "postgres://host/db?user=u&password=***");
        assert_eq!(redact_url("postgres://u@host/db"), "postgres://u@host/db");
        assert_eq!(redact_url("sqlite://facegate.db"), "sqlite://facegate.db");
        assert_eq!(redact_url("sqlite:///data/a@b.db"), "sqlite:///data/a@b.db");
    }
}
