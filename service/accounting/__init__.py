"""Who asked and what it cost: tenants by API key (``tenants``), the quota lease before inference and its settlement
(``billing``), the usage ledger behind one database URL (``ledger``) and the Prometheus metrics of one app
(``metrics``)."""
