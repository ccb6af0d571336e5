"""A part of MatcherNode (matcher.py), as a mixin: its identity in a shared map (issue 29) — the
robot_id parameter, the session a mapping matcher starts at each run (and on ~/new_session), and
what ~/info says of them. What a session is: lln_ros.mapstore.sessions."""

from __future__ import annotations

import socket

from std_srvs.srv import Trigger

from ..errors import LLNError
from ..mapstore.sessions import SessionLog, check_robot_id, robot_from_namespace
from .common import failed_response, guarded


class FleetIdentity:
    """robot_id, the mapping session and ~/new_session (state: MatcherNode's params, loc, store)."""

    def start_session(self, p: dict) -> None:
        """ValueError (the node does not start) for a robot_id that cannot name a robot."""
        self.robot_id = check_robot_id(
            p['robot_id'] or robot_from_namespace(self.get_namespace(), socket.gethostname())
        )
        if p['mode'] == 'mapping':  # only a mapping matcher stores keyframes, so only it has a session
            self.loc.session = SessionLog(self.store, self.robot_id)
            s = self.loc.session.session
            self.get_logger().info(f'robot {s.robot}: session {s.id} ({s.label}) in map {self.store.path}')
        self.create_service(Trigger, '~/new_session', self.on_new_session)

    @guarded('~/new_session', failed_response)
    def on_new_session(self, request, response):
        def new():
            if self.loc.session is None:
                raise LLNError('no session to renew: a matcher in localization mode stores no keyframes')
            s = self.loc.session.new()
            return f'robot {s.robot}: session {s.id} ({s.label}) started'

        return self._service(response, new)

    def session_info(self) -> dict:
        """~/info's identity part: this robot, its session (None in localization mode), every session."""
        log = self.loc.session
        mine = None if log is None else {'id': log.session.id, 'label': log.session.label, 'keyframes': log.count}
        every = [{'id': s.id, 'robot': s.robot, 'label': s.label} for s in self.store.sessions()]
        return {'robot_id': self.robot_id, 'session': mine, 'sessions': every}
