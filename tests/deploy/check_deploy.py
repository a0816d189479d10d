#!/usr/bin/env python3
"""What deploy/ holds that cannot run here is still checked: nginx -t on the load balancer's
config, the compose file and the Kubernetes manifests parsed (python3-yaml) with the shape they
promise, and every surfel-server / surfel-worker flag they (and the systemd units) pass is one the
binaries' --help lists."""
import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import yaml

failures = []


def check(ok, what):
    print(("ok   " if ok else "FAIL ") + what)
    if not ok:
        failures.append(what)


def flags_of(binary):
    out = subprocess.run([binary, "--help"], capture_output=True, text=True, check=True).stdout
    return set(re.findall(r"(--[a-z][a-z0-9-]*)", out))


def check_args(args, known, where):
    used = [a for a in args if isinstance(a, str) and a.startswith("--")]
    unknown = [a for a in used if a not in known]
    check(not unknown, f"{where}: flags {used} known to the binary (unknown: {unknown})")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--deploy-dir", required=True)
    ap.add_argument("--bin-dir", required=True)
    a = ap.parse_args()
    deploy = Path(a.deploy_dir)
    flags = {"surfel-server": flags_of(f"{a.bin_dir}/surfel-server"),
             "surfel-worker": flags_of(f"{a.bin_dir}/surfel-worker")}

    # nginx -t. The upstreams are compose service names, which resolve only inside compose's
    # network; nginx resolves them when it loads, so the check maps them to 127.0.0.1.
    nginx = shutil.which("nginx") or "/usr/sbin/nginx"
    conf = (deploy / "nginx.conf").read_text()
    check("grpc_pass grpc://surfel_api" in conf, "nginx.conf passes gRPC to the upstream")
    with tempfile.TemporaryDirectory() as prefix:
        local = Path(prefix) / "nginx.conf"
        local.write_text(re.sub(r"server (server-[ab]):", "server 127.0.0.1:", conf))
        (Path(prefix) / "logs").mkdir()
        r = subprocess.run([nginx, "-t", "-p", prefix, "-c", str(local), "-g",
                            f"pid {prefix}/nginx.pid; error_log {prefix}/logs/error.log;"],
                           capture_output=True, text=True)
        check(r.returncode == 0 and "test is successful" in r.stderr, "nginx -t: " + r.stderr.strip())

    # docker-compose.yml: postgres, 2 servers (API nodes), 3 workers, nginx; one blob volume.
    compose = yaml.safe_load((deploy / "docker-compose.yml").read_text())
    services = compose["services"]
    check(set(services) == {"postgres", "server-a", "server-b", "worker", "nginx"},
          f"compose services: {sorted(services)}")
    check(services["worker"]["deploy"]["replicas"] == 3, "compose: 3 workers")
    for name in ("server-a", "server-b", "worker"):
        cmd = services[name]["command"]
        check(cmd[0] in flags, f"compose {name}: runs {cmd[0]}")
        check_args(cmd, flags[cmd[0]], f"compose {name}")
        check(any(str(c).startswith("postgres://") for c in cmd), f"compose {name}: a postgres store")
        check("blobs:/blobs" in services[name]["volumes"], f"compose {name}: the shared blob volume")
    check(services["server-a"]["command"][services["server-a"]["command"].index("--workers") + 1] == "0",
          "compose servers are API nodes (--workers 0)")
    check("./nginx.conf:/etc/nginx/nginx.conf:ro" in services["nginx"]["volumes"], "compose nginx: our config")

    # Kubernetes: Deployments for server and worker, a Service, the URL from a Secret, an RWX volume.
    docs = [d for d in yaml.safe_load_all((deploy / "k8s" / "surfel.yaml").read_text()) if d]
    kinds = sorted(f"{d['kind']}/{d['metadata']['name']}" for d in docs)
    check(kinds == ["Deployment/surfel-server", "Deployment/surfel-worker",
                    "PersistentVolumeClaim/surfel-blobs", "Service/surfel"], f"k8s objects: {kinds}")
    by = {d["metadata"]["name"]: d for d in docs}
    check(by["surfel-blobs"]["spec"]["accessModes"] == ["ReadWriteMany"], "k8s: blobs volume is ReadWriteMany")
    check(by["surfel"]["spec"]["selector"] == by["surfel-server"]["spec"]["template"]["metadata"]["labels"],
          "k8s: the Service selects the server pods")
    for name in ("surfel-server", "surfel-worker"):
        pod = by[name]["spec"]["template"]["spec"]
        c = pod["containers"][0]
        check(c["args"][0] == name, f"k8s {name}: runs {name}")
        check_args(c["args"], flags[name], f"k8s {name}")
        env = {e["name"]: e for e in c["env"]}
        check(env["SURFEL_STORE"]["valueFrom"]["secretKeyRef"]["name"] == "surfel-store",
              f"k8s {name}: the store URL from the Secret")
        check(any(v.get("persistentVolumeClaim", {}).get("claimName") == "surfel-blobs" for v in pod["volumes"]),
              f"k8s {name}: mounts the blobs")

    # systemd units: the flags of ExecStart.
    for unit, binary in (("surfel-server.service", "surfel-server"), ("surfel-worker.service", "surfel-worker")):
        text = (deploy / unit).read_text().replace("\\\n", " ")
        exec_start = next(l for l in text.splitlines() if l.startswith("ExecStart="))
        check(f"/{binary} " in exec_start, f"{unit}: runs {binary}")
        check_args(exec_start.split(), flags[binary], unit)

    if failures:
        print(f"{len(failures)} checks failed", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
