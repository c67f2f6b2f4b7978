"""deploy/ as written (issue #28): the recipes name what exists and pass every option through.

No Docker daemon or batch system runs here, so the files are checked for what makes them run:
the paths the Dockerfiles copy exist, the images the manifests name are the ones the
Dockerfiles build, the DaskJob's command parses, jobqueue.py forwards every `pwf-dask run`
option and its resources, and the batch scripts are valid bash.
"""

import importlib.metadata
import importlib.util
import subprocess
import sys
import types
from pathlib import Path

import pytest
import yaml

from pwf_dask import cli

ROOT = Path(__file__).resolve().parents[1]
DEPLOY = ROOT / "deploy"


def instructions(dockerfile: Path) -> list[tuple[str, str]]:
    text = dockerfile.read_text().replace("\\\n", " ")
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    return [(line.split()[0].upper(), line.split(None, 1)[1] if " " in line else "") for line in lines]


@pytest.mark.parametrize("name,tag", [("Dockerfile", "pwf-dask:cpu"), ("Dockerfile.cuda", "pwf-dask:cuda")])
def test_dockerfiles_copy_what_exists_and_install_known_extras(name, tag):
    path = DEPLOY / name
    ins = instructions(path)
    known = {"FROM", "ENV", "WORKDIR", "COPY", "RUN", "USER", "ENTRYPOINT", "CMD", "ARG"}
    assert ins[0][0] == "FROM" and {k for k, _ in ins} <= known
    for kind, rest in ins:
        if kind == "COPY":
            *sources, _ = rest.split()
            for s in sources:
                assert (ROOT / s).exists(), (name, s)
    extras = set(importlib.metadata.metadata("pwf-dask").get_all("Provides-Extra"))
    installs = " ".join(rest for kind, rest in ins if kind == "RUN")
    for spec in installs.split():
        if spec.strip('"').startswith(".["):
            assert set(spec.strip('"')[2:-1].split(",")) <= extras, spec
    assert f"-t {tag} ." in path.read_text()  # the build command its header documents


def manifests():
    return [yaml.safe_load(p.read_text()) for p in sorted((DEPLOY / "kubernetes").glob("*.yaml"))]


def containers(node):
    if isinstance(node, dict):
        for k, v in node.items():
            if k == "containers":
                yield from v
            else:
                yield from containers(v)
    elif isinstance(node, list):
        for v in node:
            yield from containers(v)


def test_kubernetes_manifests_name_the_cuda_image_and_the_daskjob_command_parses():
    docs = manifests()
    assert {d["kind"] for d in docs} == {"DaskCluster", "DaskJob"}
    for doc in docs:
        for c in containers(doc):
            assert c["image"].endswith("/pwf-dask:cuda"), c["image"]
    job = next(d for d in docs if d["kind"] == "DaskJob")
    (runner,) = job["spec"]["job"]["spec"]["containers"]
    argv = [a.replace("$(DASK_SCHEDULER_ADDRESS)", "tcp://scheduler:8786") for a in runner["args"]]
    assert argv[0] == "pwf-dask"
    args = cli.build_parser().parse_args(argv[1:])
    assert args.command == "run" and args.scheduler.startswith("tcp://") and args.device == "gpu"
    workers = job["spec"]["cluster"]["spec"]["worker"]["spec"]["containers"][0]
    assert workers["args"][:2] == ["dask", "worker"] and "GPU=1" in workers["args"]


def load_jobqueue():
    spec = importlib.util.spec_from_file_location("jobqueue_recipe", DEPLOY / "jobqueue.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_jobqueue_accepts_every_run_option_and_forwards_it():
    jq = load_jobqueue()
    run = cli.build_parser()._subparsers._group_actions[0].choices["run"]
    # the recipe makes the scheduler connection itself (its cluster's dashboard and security)
    local_only = {"--scheduler", "--device", "--figures", "--dashboard-address", "--security", "--help", "-h"}
    wanted = {o for a in run._actions for o in a.option_strings} - local_only
    have = {o for a in jq.parser()._actions for o in a.option_strings}
    assert wanted <= have, wanted - have
    options = ["--max-iter", "77", "--alpha", "paper", "--angle-chain", "3", "--diffuser-model", "zero-phase"]
    ours = jq.parser().parse_args(["slurm", "s.zarr", "r.zarr", *options])
    theirs = cli.build_parser().parse_args(["run", "s.zarr", "r.zarr", *options])
    assert cli.retrieval_kwargs(ours) == cli.retrieval_kwargs(theirs)


@pytest.mark.parametrize(
    "system,cls,gpu", [("slurm", "SLURMCluster", "--gres=gpu:1"), ("pbs", "PBSCluster", "-l ngpus=1")]
)
def test_jobqueue_takes_resources_and_the_environment_from_the_command_line(monkeypatch, system, cls, gpu):
    made = {}
    fake = types.ModuleType("dask_jobqueue")
    setattr(fake, cls, lambda **kw: made.update(kw) or "cluster")
    monkeypatch.setitem(sys.modules, "dask_jobqueue", fake)
    jq = load_jobqueue()
    argv = [system, "s.zarr", "r.zarr", "--queue", "a100", "--cores", "8", "--memory", "64GB"]
    argv += ["--walltime", "06:00:00", "--activate", "source /env/bin/activate"]
    assert jq.make_cluster(jq.parser().parse_args(argv)) == "cluster"
    assert made["queue"] == "a100" and made["cores"] == 8 and made["memory"] == "64GB"
    assert made["walltime"] == "06:00:00" and made["job_script_prologue"] == ["source /env/bin/activate"]
    assert made["job_extra_directives"] == [gpu] and made["worker_extra_args"][-2:] == ["--resources", "GPU=1"]


def test_jobqueue_refuses_a_bad_number_before_queueing_a_job(monkeypatch):
    jq = load_jobqueue()
    monkeypatch.setattr(jq, "make_cluster", lambda args: pytest.fail("a job was queued"))
    with pytest.raises(ValueError, match="max_iter"):
        jq.main(["slurm", "s.zarr", "r.zarr", "--max-iter", "0"])


@pytest.mark.parametrize("script", sorted(p.name for p in (DEPLOY / "batch").iterdir()))
def test_batch_scripts_are_valid_bash_running_pwf_dask(script):
    path = DEPLOY / "batch" / script
    assert subprocess.run(["bash", "-n", str(path)], capture_output=True).returncode == 0
    text = path.read_text()
    assert "pwf-dask run" in text and "--scheduler local-cuda" in text and "activate" in text
