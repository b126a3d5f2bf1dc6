"""DRVS benchmarks: reproducible measurements that write JSON and PNG (run with drvs-bench)."""
