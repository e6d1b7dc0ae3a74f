package com.tbp.agent;

import java.io.Closeable;
import java.io.IOException;
import java.util.concurrent.CountDownLatch;

/** An agent whose camera never finishes closing, run as its own process by {@link ExitDeadlineTest}. */
public final class HangingCloseAgent {

    private HangingCloseAgent() {
    }

    public static void main(String[] args) throws Exception {
        final Fakes.Camera camera = new Fakes.Camera() {
            @Override
            public void close() {
                try {
                    new CountDownLatch(1).await();  // a HAL that never returns
                } catch (InterruptedException e) {
                    Thread.currentThread().interrupt();
                }
            }
        };
        Platform platform = new Platform() {
            @Override
            public Log log() {
                return new Fakes.Recorder();
            }

            @Override
            public CameraBackend openCamera(double exposureS, long iso) {
                return camera;
            }

            @Override
            public ImageStore imageStore() {
                try {
                    return new ImageStore(Fakes.folder(), new Fakes.Disk());
                } catch (IOException e) {
                    throw new AssertionError(e);
                }
            }

            @Override
            public Closeable listen(String name, Agent agent) {
                return new Closeable() {
                    @Override
                    public void close() {
                    }
                };
            }
        };
        System.exit(Launcher.run(args, platform, System.in, System.out));
    }
}
