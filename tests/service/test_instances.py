"""Several instances: discovery by liveliness, the shared plan key, round-robin load
spreading over planning-only instances, and an instance leaving."""
from __future__ import annotations

import time
from collections import Counter

import numpy as np
import pytest

from service.client import FalconClient, PlanBalancer, wait_for_instance
from service.config import SessionSettings

from service.testing import GOAL_A_M, HOME_M, PREFIX, client_for, endpoint, running_service


def test_instances_are_found_by_liveliness_and_share_the_plan_load(model):
    first_ep, second_ep = endpoint(), endpoint()
    with running_service("plan1", "none", model, listen=first_ep) as first, \
            running_service("plan2", "none", model, listen=second_ep, connect=(first_ep,)), \
            client_for(first, "plan1") as client:
        # the client connects to plan1 only; gossip tells it where plan2 is
        deadline = time.monotonic() + 10
        while client.instances() != ["plan1", "plan2"] and time.monotonic() < deadline:
            time.sleep(0.05)
        assert client.instances() == ["plan1", "plan2"]
        balancer = PlanBalancer(client, planning_only=True)
        try:
            answers = [balancer.plan(HOME_M, GOAL_A_M, request_id=f"rr{i}") for i in range(6)]
            assert [a["request_id"] for a in answers] == [f"rr{i}" for i in range(6)]
            assert Counter(a["instance"] for a in answers) == {"plan1": 3, "plan2": 3}
            trajectories = {a["instance"]: a["trajectory"] for a in answers}
            # same planner, same answer -- to the solver's tolerance, since the service
            # warm-starts from solved neighbours (the instances here share one process)
            one, two = trajectories["plan1"], trajectories["plan2"]
            assert one["duration_s"] == pytest.approx(two["duration_s"], rel=1e-5)
            assert np.allclose(one["position_m"], two["position_m"], atol=1e-6)   # < 1 um
            # the shared key is served by exactly one instance per request
            replies = list(client.session.get(f"{PREFIX}/plan", timeout=10.0, payload=(
                b'{"start_m": [0, 0, 0.1448], "goal_m": [0.02, 0.01, 0.13]}')))
            assert len(replies) == 1 and replies[0].ok is not None
        finally:
            balancer.close()
    # plan2 closed first: its token is gone from the first's point of view too
    with running_service("plan3", "none", model) as third, client_for(third, "plan3") as client:
        assert client.instances() == ["plan3"]


def test_a_client_mode_session_reaches_an_instance(model):
    """``--mode client``: a session that joins another node rather than peering."""
    with running_service("cm0", "none", model) as service, \
            FalconClient(SessionSettings.client(service.settings.listen, mode="client"), prefix=PREFIX,
                         instance="cm0") as client:
        wait_for_instance(client, "cm0")
        assert client.info()["instance"] == "cm0"
        assert client.session.info.peers_zid() and not client.session.info.routers_zid()
