"""The Drums monitoring mixin: recording rules, alerts and Grafana dashboards that belong together,
rendered from one config (config.yaml, expected_rates.yaml) by `python -m deploy.mixin.build`."""
