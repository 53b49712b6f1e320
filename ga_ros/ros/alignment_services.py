"""``std_srvs/Trigger`` services of the alignment node: ``~/finish_track``, ``~/reset``,
``~/save_state``, ``~/load_state`` (mixin of :class:`~ga_ros.ros.alignment_node.AlignmentNode`)."""



from std_srvs.srv import Trigger

from ga_ros.errors import SolverError


class AlignmentServices:
    """Services of :class:`~ga_ros.ros.alignment_node.AlignmentNode`."""

    def _create_services(self) -> None:
        """The ``std_srvs/Trigger`` services."""
        self.create_service(Trigger, '~/finish_track', self._srv_finish_track)
        self.create_service(Trigger, '~/reset', self._srv_reset)
        self.create_service(Trigger, '~/save_state', self._srv_save)
        self.create_service(Trigger, '~/load_state', self._srv_load)

    def _srv_finish_track(self, request: Trigger.Request,
                          response: Trigger.Response) -> Trigger.Response:
        if not self.settings.allow_finish_track:
            response.success = False
            response.message = ('finish_track is disabled (parameter allow_finish_track: false; '
                                'tracks end by the next track, the end-of-input message or '
                                'track_idle_timeout_sec)')
            return response
        try:
            update = self._finish_track()
        except SolverError as exc:
            response.success, response.message = False, f'solver failed: {exc}'
            return response
        except Exception as exc:  # noqa: BLE001 - a service must answer
            response.success, response.message = False, f'{type(exc).__name__}: {exc}'
            return response
        if update is None:
            response.success, response.message = True, 'no open track'
            return response
        response.success = True
        response.message = (f'track {update.track_id}: {update.iterations} iterations, '
                            f'sigma0^2 {update.sigma0_sq:.4g}, {update.update_ms:.1f} ms')
        return response

    def _srv_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self.settings.allow_reset:
            response.success = False
            response.message = 'reset is disabled (parameter allow_reset: false)'
            return response
        self._drain()
        try:
            self.session.reset()
        except Exception as exc:  # noqa: BLE001 - a service must answer
            response.success, response.message = False, f'reset refused: {exc}'
            return response
        self._datum_saved = False  # the datum file went with the state: saved again when known
        self._new_survey_inputs()
        self.corrections.restart()  # consumers drop what they held: a full message next
        self.paths.restart()
        self._publish_all()
        response.success, response.message = True, 'state cleared'
        return response

    def _srv_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        path = self.settings.state_file
        if not path:
            response.success, response.message = False, 'parameter state_file is empty'
            return response
        self._drain()
        try:
            self.session.save(path)
        except Exception as exc:  # noqa: BLE001 - a service must answer
            response.success, response.message = False, f'save failed: {exc}'
            return response
        response.success, response.message = True, f'saved to {path}'
        return response

    def _srv_load(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self.settings.allow_load_state:
            response.success = False
            response.message = 'load_state is disabled (parameter allow_load_state: false)'
            return response
        self._drain()
        try:
            how = self.session.load()
        except Exception as exc:  # noqa: BLE001 - a service must answer
            path = self.settings.state_file
            response.success = False
            response.message = (f'no state file {path!r}' if 'no state file' in str(exc)
                                else f'load failed (state unchanged): {exc}')
            return response
        self._restore_datum()
        # the standard inputs continue after the loaded nodes, as after a start (a fresh
        # keyframe chain bridged to the loaded newest node), and map -> odom is the loaded one
        self._continue_inputs()
        self._resumed = True
        self.odom.restore(self.session.map_odom)
        self.corrections.restart()  # consumers drop what they held: a full message next
        self.paths.restart()
        self._publish_all()
        response.success = True
        response.message = (f'loaded {self.session.n_nodes()} nodes from '
                            f'{self.settings.state_file} ({how})')
        return response

