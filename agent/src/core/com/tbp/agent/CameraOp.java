package com.tbp.agent;

/** A focus or capture request waiting for (or holding) the camera. */
final class CameraOp {

    final Connection connection;
    final long id;
    final boolean capture;
    final double diopters;
    final double exposureS;
    final long iso;

    private CameraOp(Connection connection, long id, boolean capture, double diopters, double exposureS, long iso) {
        this.connection = connection;
        this.id = id;
        this.capture = capture;
        this.diopters = diopters;
        this.exposureS = exposureS;
        this.iso = iso;
    }

    static CameraOp focus(Connection connection, long id, double diopters) {
        return new CameraOp(connection, id, false, diopters, 0, 0);
    }

    static CameraOp capture(Connection connection, long id, double exposureS, long iso) {
        return new CameraOp(connection, id, true, 0, exposureS, iso);
    }

    String name() {
        return capture ? "capture" : "focus";
    }
}
